// registerSectionFiles with a stack of every Allen id (`atlas slice --regions all`): the
// registration gets the major regions for its geometric stages and damage check and fits the map
// to every region of the section's own contrast (the region warp, docs/registration.md); the
// results keep every id. Ground truth: second-family sections (every id stained at its own
// level) generated from the stack's own slices of the real CCFv3 annotation.
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/section_generator_b.hpp"

#include <gtest/gtest.h>

#include <unistd.h>

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

} // namespace

TEST_F(RegistrationServiceTest, AStackOfEveryRegionIsFittedToEveryRegionAndKeepsItsIds) {
    AtlasSliceRequest sq;
    sq.volume = kAllen / "annotation_50.nrrd";
    sq.ontology = kAllen / "structure_tree_safe_2017.csv";
    sq.intervalUm = 1500;
    sq.firstUm = 5000;
    sq.umPerPx = 25;
    sq.regions = "all";
    sq.output = dir_ / "stack";
    auto made = runAtlasSlice(sq);
    ASSERT_TRUE(made) << made.error().message;
    auto stack = readStack(sq.output);
    ASSERT_TRUE(stack) << stack.error().message;
    auto ontology = core::readOntologyCsv(sq.ontology);
    ASSERT_TRUE(ontology) << ontology.error().message;
    const std::set<std::uint32_t> major(pipeline::majorRegionIds().begin(),
                                        pipeline::majorRegionIds().end());

    double sum[2] = {0, 0};
    int kept = 0;
    for (int slice : {1, 2}) { // 6500 and 8000 um: striatum and thalamus; hippocampus, midbrain
        auto labels = readStackSlice(*stack, slice);
        ASSERT_TRUE(labels) << labels.error().message;
        sim::GeneratorOptionsB go;
        go.seed = 4100 + std::uint64_t(slice);
        auto gen = sim::generateSectionB(*labels, *ontology, go);
        ASSERT_TRUE(gen) << gen.error().message;
        const fs::path image = dir_ / ("section-" + std::to_string(slice) + ".tif");
        ASSERT_TRUE(core::writeImage(image, gen->image));
        for (int v = 0; v < 2; ++v) {
            RegisterRequest rq;
            auto path = stackSlicePath(*stack, slice);
            ASSERT_TRUE(path);
            rq.atlas = *path;
            rq.atlasSlice = sliceFrame(*stack, slice);
            rq.stackRegions = stack->regions;
            rq.regionWarp = v == 1;
            rq.image = image;
            rq.points = dir_ / "points.csv";
            rq.warpedLabels = dir_ / "labels.tif";
            rq.output =
                dir_ / ("result-" + std::to_string(slice) + "-" + std::to_string(v) + ".json");
            std::vector<cv::Point2d> pts;
            for (const sim::Landmark& l : gen->truth.landmarks)
                pts.push_back(l.image);
            auto reg = registerSectionFiles(
                rq, [&](const fs::path&) -> core::Result<std::vector<cv::Point2d>> { return pts; });
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
        }
    }
    // Measured (gcc, RelWithDebInfo): 3.89 -> 3.82 and 3.26 -> 2.87 px, both kept; over the
    // stack's five slices 7.91 -> 7.59 (summed), never worse. The 50 um annotation cut at 25 um
    // is blockier than the benchmark's 25 um planes, where the stage gains more (docs).
    EXPECT_GE(kept, 1);
    EXPECT_LT(sum[1], sum[0]) << "without " << sum[0] / 2 << ", with " << sum[1] / 2;
}
