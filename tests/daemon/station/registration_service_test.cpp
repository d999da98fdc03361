// registerSectionFiles with a stack of every Allen id (`atlas slice --regions all`): the
// registration gets the major regions for its geometric stages and damage check and fits the map
// to every region of the section's own contrast (the region warp, docs/registration.md); the
// results keep every id. Ground truth: second-family sections (every id stained at its own
// level) generated from the stack's own slices of the real CCFv3 annotation.
// The same for a stack of major regions, whose slices keep every id in a plane of their own.
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/section_generator_b.hpp"

#include <gtest/gtest.h>

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <set>

using namespace slicestation;
using namespace slicestation::daemon;
namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const fs::path kAllen = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";
const fs::path kOntology = kAllen / "structure_tree_safe_2017.csv";

class RegistrationServiceTest : public ::testing::Test {
protected:
    void SetUp() override {
        if (!fs::exists(kAllen / "annotation_50.nrrd"))
            GTEST_SKIP() << "../shared/atlas is absent: the real annotation is not available";
        dir_ = fs::temp_directory_path() / ("slst-regsvc-" + std::to_string(::getpid()));
        fs::remove_all(dir_);
        fs::create_directories(dir_);
    }
    void TearDown() override {
        if (!dir_.empty())
            fs::remove_all(dir_);
    }
    /// The 50 um annotation cut every 1500 um from 5000 um at 25 um per pixel into dir_/`name`.
    core::Result<AtlasStack> cutStack(const std::string& regions, const std::string& name) {
        AtlasSliceRequest sq;
        sq.volume = kAllen / "annotation_50.nrrd";
        sq.ontology = kOntology;
        sq.intervalUm = 1500;
        sq.firstUm = 5000;
        sq.umPerPx = 25;
        sq.regions = regions;
        sq.output = dir_ / name;
        if (auto made = runAtlasSlice(sq); !made)
            return made.error();
        return readStack(sq.output);
    }
    fs::path dir_;
};

double rmse(const pipeline::Registration& reg, const std::vector<sim::Landmark>& landmarks) {
    double sum = 0;
    for (const sim::Landmark& l : landmarks) {
        const cv::Point2d d = reg.atlasFromImage(l.image) - l.atlas;
        sum += d.dot(d);
    }
    return std::sqrt(sum / double(std::max<std::size_t>(1, landmarks.size())));
}

/// A second-family section of `labels` (every id stained at its own level), written to `image`.
core::Result<sim::GeneratedSectionB> sectionB(const cv::Mat& labels, const core::Ontology& ontology,
                                              std::uint64_t seed, const fs::path& image) {
    sim::GeneratorOptionsB go;
    go.seed = seed;
    auto gen = sim::generateSectionB(labels, ontology, go);
    if (!gen)
        return gen.error();
    if (auto w = core::writeImage(image, gen->image); !w)
        return w.error();
    return gen;
}

/// `rq` registered with the landmarks' section pixels as its points, the warped labels kept.
core::Result<RegisteredSection> registerLandmarks(RegisterRequest rq, const fs::path& dir,
                                                  const std::vector<sim::Landmark>& landmarks) {
    std::vector<cv::Point2d> pts;
    for (const sim::Landmark& l : landmarks)
        pts.push_back(l.image);
    rq.points = dir / "points.csv";
    rq.warpedLabels = dir / "labels.tif";
    return registerSectionFiles(
        rq, [&](const fs::path&) -> core::Result<std::vector<cv::Point2d>> { return pts; });
}

} // namespace

TEST_F(RegistrationServiceTest, AStackOfEveryRegionIsFittedToEveryRegionAndKeepsItsIds) {
    auto stack = cutStack("all", "stack");
    ASSERT_TRUE(stack) << stack.error().message;
    auto ontology = core::readOntologyCsv(kOntology);
    ASSERT_TRUE(ontology) << ontology.error().message;
    const std::set<std::uint32_t> major(pipeline::majorRegionIds().begin(),
                                        pipeline::majorRegionIds().end());

    double sum[2] = {0, 0};
    int kept = 0;
    for (int slice : {1, 2}) { // 6500 and 8000 um: striatum and thalamus; hippocampus, midbrain
        auto labels = readStackSlice(*stack, slice);
        ASSERT_TRUE(labels) << labels.error().message;
        const fs::path image = dir_ / ("section-" + std::to_string(slice) + ".tif");
        auto gen = sectionB(*labels, *ontology, 4100 + std::uint64_t(slice), image);
        ASSERT_TRUE(gen) << gen.error().message;
        for (int v = 0; v < 2; ++v) {
            RegisterRequest rq;
            auto path = stackSlicePath(*stack, slice);
            ASSERT_TRUE(path);
            rq.atlas = *path;
            rq.atlasSlice = sliceFrame(*stack, slice);
            rq.stackRegions = stack->regions;
            rq.regionWarp = v == 1;
            rq.image = image;
            rq.output =
                dir_ / ("result-" + std::to_string(slice) + "-" + std::to_string(v) + ".json");
            auto reg = registerLandmarks(rq, dir_, gen->truth.landmarks);
            ASSERT_TRUE(reg) << reg.error().message;
            const auto& q = reg->registration.quality;
            const double e = rmse(reg->registration, gen->truth.landmarks);
            sum[v] += e;
            std::printf("slice %d, region warp %s: landmark RMSE %.2f atlas px%s\n", slice,
                        v ? "on" : "off", e, q.regionWarpKept ? " (kept)" : "");
            if (v == 1) {
                // The stage ran (it measures the start map's explained share before it decides).
                EXPECT_GT(q.regionWarpExplainedBefore, 0) << slice;
                kept += q.regionWarpKept;
            } else {
                EXPECT_EQ(q.regionWarpExplainedBefore, 0) << slice;
            }
            // The warped labels hold every id, not the major regions the registration was
            // given: most of the brain's pixels are ids below them.
            const cv::Mat& warped = reg->warpedLabels;
            ASSERT_EQ(warped.type(), CV_32S);
            int brain = 0, fine = 0;
            for (auto it = warped.begin<std::int32_t>(); it != warped.end<std::int32_t>(); ++it)
                if (*it > 0) {
                    ++brain;
                    fine += !major.count(std::uint32_t(*it));
                }
            EXPECT_GT(fine, brain / 2) << slice;
            EXPECT_EQ(reg->document.at("quality").at("region_warp_kept").get<bool>(),
                      q.regionWarpKept);
            EXPECT_EQ(reg->document.at("quality")
                          .at("region_warp_left_out")
                          .get<std::vector<std::int32_t>>(),
                      q.regionWarpLeftOut);
        }
    }
    // Measured (gcc, RelWithDebInfo): 3.89 -> 3.82 and 3.26 -> 2.87 px, both kept; over the
    // stack's five slices 7.91 -> 7.59 (summed), never worse. The 50 um annotation cut at 25 um
    // is blockier than the benchmark's 25 um planes, where the stage gains more (docs).
    EXPECT_GE(kept, 1);
    EXPECT_LT(sum[1], sum[0]) << "without " << sum[0] / 2 << ", with " << sum[1] / 2;
}

TEST_F(RegistrationServiceTest, AMajorRegionStackKeepsEveryIdForTheRegionWarpAndReportsMajorOnes) {
    // `atlas slice --regions major`: the slices hold the major regions (results name them) and
    // each slice keeps every id in a plane of its own, which the region warp fits.
    auto stack = cutStack("major", "major");
    ASSERT_TRUE(stack) << stack.error().message;
    auto ontology = core::readOntologyCsv(kOntology);
    ASSERT_TRUE(ontology) << ontology.error().message;
    std::set<std::uint32_t> major(pipeline::majorRegionIds().begin(),
                                  pipeline::majorRegionIds().end());
    major.insert(pipeline::kOtherRegionId);
    // The stack's ventricle ids are the ventricles' (and the lateral ventricle is among them).
    ASSERT_FALSE(stack->ventricleIds.empty());
    for (std::int32_t id : stack->ventricleIds)
        EXPECT_TRUE(ontology->isDescendantOf(std::uint32_t(id), pipeline::kVentricularSystemsId))
            << id;
    EXPECT_NE(std::find(stack->ventricleIds.begin(), stack->ventricleIds.end(), 81),
              stack->ventricleIds.end());

    double sum[2] = {0, 0};
    for (int slice : {1, 2}) {
        const StackSlice& s = stack->slices[std::size_t(slice)];
        ASSERT_EQ(s.idsFile, "ids-00" + std::to_string(slice) + ".tif");
        auto labels = readStackSlice(*stack, slice);
        ASSERT_TRUE(labels) << labels.error().message;
        auto idsImage = core::readImage(stack->dir / s.idsFile);
        ASSERT_TRUE(idsImage) << idsImage.error().message;
        auto ids = pipeline::labelsFromImage(*idsImage);
        ASSERT_TRUE(ids) << ids.error().message;
        // The id plane collapses to the slice's labels, pixel by pixel.
        const cv::Mat collapsed = pipeline::collapseLabels(
            *ids, *ontology, pipeline::majorRegionIds(), pipeline::kOtherRegionId);
        EXPECT_EQ(cv::countNonZero(collapsed != *labels), 0) << slice;
        const fs::path image = dir_ / ("major-section-" + std::to_string(slice) + ".tif");
        auto gen = sectionB(*ids, *ontology, 4200 + std::uint64_t(slice), image);
        ASSERT_TRUE(gen) << gen.error().message;
        for (int v = 0; v < 2; ++v) {
            RegisterRequest rq;
            rq.atlas = stack->dir / s.file;
            rq.atlasSlice = sliceFrame(*stack, slice);
            if (v == 0)
                rq.atlasSlice->idsFile.clear(); // a major stack cut before the ids were kept
            rq.stackRegions = stack->regions;
            rq.image = image;
            rq.output = dir_ / ("major-" + std::to_string(slice) + std::to_string(v) + ".json");
            auto reg = registerLandmarks(rq, dir_, gen->truth.landmarks);
            ASSERT_TRUE(reg) << reg.error().message;
            const auto& q = reg->registration.quality;
            const double e = rmse(reg->registration, gen->truth.landmarks);
            sum[v] += e;
            std::printf("major stack slice %d, %s the id plane: landmark RMSE %.2f atlas px%s\n",
                        slice, v ? "with" : "without", e, q.regionWarpKept ? " (kept)" : "");
            EXPECT_EQ(q.regionWarpExplainedBefore > 0, v == 1) << slice;
            // result.json names the id plane it was given.
            EXPECT_EQ(reg->document.at("atlas").value("ids", ""), v ? s.idsFile : "") << slice;
            // Results keep the stack's major regions.
            const cv::Mat& warped = reg->warpedLabels;
            ASSERT_EQ(warped.type(), CV_32S);
            for (auto it = warped.begin<std::int32_t>(); it != warped.end<std::int32_t>(); ++it) {
                if (*it > 0) {
                    ASSERT_TRUE(major.count(std::uint32_t(*it))) << *it;
                }
            }
        }
    }
    EXPECT_LT(sum[1], sum[0]) << "without " << sum[0] / 2 << ", with " << sum[1] / 2;

    // An id plane not of the slice's size is an error naming the manifest entry; nothing is
    // written.
    auto labels = readStackSlice(*stack, 1);
    ASSERT_TRUE(labels);
    const cv::Mat small = (*labels)(cv::Rect(0, 0, labels->cols / 2, labels->rows / 2)).clone();
    ASSERT_TRUE(core::writeImage(stack->dir / stack->slices[1].idsFile, small));
    RegisterRequest rq;
    rq.atlas = stack->dir / stack->slices[1].file;
    rq.atlasSlice = sliceFrame(*stack, 1);
    rq.stackRegions = stack->regions;
    rq.image = dir_ / "major-section-1.tif";
    rq.output = dir_ / "bad.json";
    auto bad = registerSectionFiles(rq, {});
    ASSERT_FALSE(bad);
    EXPECT_NE(bad.error().message.find("slices[1].ids"), std::string::npos) << bad.error().message;
    EXPECT_FALSE(fs::exists(rq.output));
}
