// Issue 19, item 4: the daemon registers each section to the plane the series model says, tilted
// when it is. Eight sections generated from planes of the real Allen annotation cut at a known
// tilt (LR 2.0, DV -1.5 degrees, 300 um apart) lie on a slide; the station's atlas is a straight
// stack cut from the same volume. Once six sections are on the series' line the station finds the
// brain's tilt from planes cut from the stack's volume, and the later sections are registered to
// planes cut at that tilt: recorded in the journal (found plane and its tilt), in result.json
// (the frame of the tilted plane) and beside the capture (the plane's labels). Ground truth: the
// generator's landmarks, mapped to CCF micrometres through the station's result, land nearer their
// true place than through the same capture registered to the straight slice.
#include "station_fixture.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/export/section_export.hpp"
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;
namespace fs = std::filesystem;

namespace {

constexpr double kTiltLr = 2.0, kTiltDv = -1.5;
constexpr double kFirstUm = 4000, kStepUm = 300;
constexpr int kSections = 8;
constexpr double kStackFirstUm = 2500, kStackIntervalUm = 100;

const fs::path kAtlasDir = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";

nlohmann::json readJson(const fs::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}

/// What the generator knows of one section: its true plane and landmarks, and how its image was
/// scaled onto the slide.
struct TrueSection {
    pipeline::SliceGeometry plane;        ///< the tilted plane it was cut from
    std::vector<sim::Landmark> landmarks; ///< generator px -> atlas px of that plane
    cv::Mat slideImage;                   ///< the image as placed on the slide
    double scale = 1;                     ///< slide image px per generator px
};

/// Where the capture lies in the slide image of its section: the offset of the capture's
/// top-left pixel (the camera frame is found in the image by its own content).
cv::Point2d captureOffset(const cv::Mat& slideImage, const cv::Mat& capture) {
    cv::Mat a, b, score;
    slideImage.convertTo(a, CV_32F);
    capture.convertTo(b, CV_32F);
    // Pad the slide image by the capture's size with its border level so the capture fits.
    cv::Mat padded;
    cv::copyMakeBorder(a, padded, b.rows, b.rows, b.cols, b.cols, cv::BORDER_REPLICATE);
    cv::matchTemplate(padded, b, score, cv::TM_CCOEFF_NORMED);
    cv::Point best;
    cv::minMaxLoc(score, nullptr, nullptr, nullptr, &best);
    return {double(best.x - b.cols), double(best.y - b.rows)};
}

/// Median distance in CCF micrometres between where `result` (and the saved mapping beside it)
/// puts the landmarks and where they truly are.
double medianCcfErrorUm(const nlohmann::json& result, const fs::path& resultDir,
                        const TrueSection& truth, cv::Point2d offset) {
    auto mapping = readSavedMapping(result, resultDir);
    auto frame = sliceFrameFromJson(result["atlas"]["stack"]);
    EXPECT_TRUE(mapping && frame);
    if (!mapping || !frame)
        return 1e9;
    std::vector<double> errors;
    for (const sim::Landmark& l : truth.landmarks) {
        const cv::Point2d onSlide =
            (l.image + cv::Point2d(0.5, 0.5)) * truth.scale - cv::Point2d(0.5, 0.5);
        const cv::Point2d capturePx = onSlide - offset;
        const cv::Vec3d found = ccfUm(frame->geometry, mapping->atlasFromImage(capturePx));
        const cv::Vec3d real = truth.plane.atlasUm(l.atlas.x, l.atlas.y);
        errors.push_back(cv::norm(found - real));
    }
    if (errors.empty())
        return 1e9;
    std::nth_element(errors.begin(), errors.begin() + long(errors.size() / 2), errors.end());
    return errors[errors.size() / 2];
}

class TiltedPlanesTest : public StationTest {
protected:
    void SetUp() override {
        StationTest::SetUp();
        work_ = testing_dir::perTestPath("tilted-planes-data");
        fs::remove_all(work_);
        fs::create_directories(work_);
    }
    void TearDown() override {
        StationTest::TearDown();
        fs::remove_all(work_);
    }

    /// A stack of the annotation: straight (both tilts 0) or tilted.
    void cutStack(const fs::path& out, double firstUm, double intervalUm, double lr, double dv) {
        AtlasSliceRequest rq;
        rq.volume = kAtlasDir / "annotation_50.nrrd";
        rq.ontology = kAtlasDir / "structure_tree_safe_2017.csv";
        rq.umPerPx = 25;
        rq.firstUm = firstUm;
        rq.intervalUm = intervalUm;
        rq.tiltLrDeg = lr;
        rq.tiltDvDeg = dv;
        rq.output = out;
        auto r = runAtlasSlice(rq);
        ASSERT_TRUE(r) << r.error().message;
    }

    /// Sections generated from the tilted planes, at the camera's pixel size, on one slide.
    void makeSlide() {
        cutStack(work_ / "tilted", kFirstUm, kStepUm, kTiltLr, kTiltDv);
        auto tilted = readStack(work_ / "tilted");
        ASSERT_TRUE(tilted) << tilted.error().message;
        std::vector<fs::path> images;
        for (int i = 0; i < kSections; ++i) {
            char name[64];
            std::snprintf(name, sizeof name, "slice-%03d.tif", i);
            auto labels = core::readImage(work_ / "tilted" / name);
            ASSERT_TRUE(labels) << labels.error().message;
            sim::GeneratorOptions o;
            o.seed = 500 + std::uint64_t(i);
            o.imageSize = {1000, 740};
            auto gen = sim::generateSection(*labels, o);
            ASSERT_TRUE(gen) << gen.error().message;
            // The generator's pixel size, from its atlas-from-image map (atlas pixels of 25 um).
            const auto& a = gen->truth.affineAtlasFromImage;
            const double um = std::sqrt(std::abs(a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0))) * 25;
            cv::Mat scaled;
            cv::resize(gen->image, scaled, {}, um / kUmPerPx, um / kUmPerPx, cv::INTER_AREA);
            images.push_back(work_ / ("section-" + std::to_string(i) + ".tif"));
            ASSERT_TRUE(core::writeImage(images.back(), scaled));
            truth_.push_back({tilted->slices[std::size_t(i)].geometry, gen->truth.landmarks, scaled,
                              double(scaled.cols) / gen->image.cols});
        }
        auto s = sim::loadVirtualSlide(images, kUmPerPx, 4, 14'000);
        ASSERT_TRUE(s) << s.error().message;
        s->originXUm = s->originYUm = 1'000;
        for (auto& sec : s->sections) {
            sec.centre.xUm += 1'000;
            sec.centre.yUm += 1'000;
        }
        slide__ = std::move(*s);
        slide_ = &slide__;
        stageLimits_ = hw::StageLimits{{0, 70'000}, {0, 40'000}, hw::AxisRange{0, 5'000}};
    }

    fs::path work_;
    sim::VirtualSlide slide__;
    std::vector<TrueSection> truth_;
};

} // namespace

TEST_F(TiltedPlanesTest, LaterSectionsAreRegisteredToPlanesCutAtTheFoundTilt) {
    if (!fs::exists(kAtlasDir / "annotation_50.nrrd"))
        GTEST_SKIP() << "no Allen annotation under " << kAtlasDir;
    cutStack(work_ / "stack", kStackFirstUm, kStackIntervalUm, 0, 0);
    makeSlide();
    if (HasFatalFailure())
        return;
    daemonExtra_ = "atlas = \"" + (work_ / "stack").string() + "\"\n";
    build();
    std::vector<PlanEntry> planned;
    for (int i = 0; i < kSections; ++i)
        planned.push_back(
            entryOf(slide__, i,
                    int(std::lround((kFirstUm + kStepUm * i - kStackFirstUm) / kStackIntervalUm))));
    const RunRecord run = runToTheEnd(planOf(planned, "tilted"));
    EXPECT_EQ(run.doneCount, kSections);

    auto sections = rig_.station->journal().sections(run.id);
    ASSERT_TRUE(sections);
    ASSERT_EQ(sections->size(), std::size_t(kSections));
    int tilted = 0;
    double tiltedErrorUm = 0, straightErrorUm = 0;
    for (int i = 0; i < kSections; ++i) {
        const SectionRecord& s = (*sections)[std::size_t(i)];
        SCOPED_TRACE(s.name);
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_TRUE(regs);
        ASSERT_EQ(regs->size(), 1u);
        const RegistrationRecord& r = regs->front();
        ASSERT_TRUE(r.foundTiltLrDeg.has_value());
        ASSERT_TRUE(r.foundTiltDvDeg.has_value());
        std::printf("%s slice %d tilt %.2f / %.2f quality %.3f score %.2f %s\n", s.name.c_str(),
                    r.atlasSlice, *r.foundTiltLrDeg, *r.foundTiltDvDeg, r.quality,
                    r.damageScore.value_or(-1), r.warning.c_str());
        const nlohmann::json result = readJson(rig_.dir / r.resultPath);
        const nlohmann::json& frame = result["atlas"]["stack"];
        const nlohmann::json plane = planeJson(r);
        if (*r.foundTiltLrDeg == 0 && *r.foundTiltDvDeg == 0) {
            // Before the tilt is known: the stack's straight slice.
            EXPECT_LT(i, SeriesTracker::kTiltFirstSections + 1) << "the tilt was never applied";
            EXPECT_EQ(plane["found"]["tilted"], false);
            EXPECT_NEAR(frame["normal"][1].get<double>(), 0, 1e-9);
            EXPECT_NEAR(frame["normal"][2].get<double>(), 0, 1e-9);
            continue;
        }
        ++tilted;
        // The found tilt is the brain's within a degree. From six to eight sections the search
        // is that close, not closer: DV -0.75 then -1.11 in the release build, -1.06 then -0.88
        // in the checking build (clang, sanitizers) against -1.5; the 0.5 degree is
        // measured on whole generated series in slst_bench_series (docs/atlas.md).
        EXPECT_NEAR(*r.foundTiltLrDeg, kTiltLr, 1.0);
        EXPECT_NEAR(*r.foundTiltDvDeg, kTiltDv, 1.0);
        EXPECT_EQ(plane["found"]["tilted"], true);
        // result.json's frame is the tilted plane's: its normal leans by the found angles (a
        // coronal normal is AP; the lean shows in DV and LR), through the slice's position.
        const double n0 = frame["normal"][0].get<double>();
        EXPECT_GT(std::abs(frame["normal"][1].get<double>()) +
                      std::abs(frame["normal"][2].get<double>()),
                  std::sin(1.0 * CV_PI / 180));
        EXPECT_GT(n0, std::cos(5.0 * CV_PI / 180));
        EXPECT_DOUBLE_EQ(frame["position_um"].get<double>(), *r.foundPositionUm);
        // The plane registered to lies beside the capture and result.json names it.
        const std::string atlasFile = result["atlas"]["file"].get<std::string>();
        EXPECT_NE(atlasFile.find(".plane.tif"), std::string::npos) << atlasFile;
        EXPECT_TRUE(fs::exists((rig_.dir / r.resultPath).parent_path() / atlasFile)) << atlasFile;
        // So does the tilted plane of every id (the stack's slices keep theirs: major regions),
        // which the region warp fitted.
        const std::string idsFile = result["atlas"].value("ids", "");
        EXPECT_NE(idsFile.find(".plane-ids.tif"), std::string::npos) << idsFile;
        EXPECT_TRUE(fs::exists((rig_.dir / r.resultPath).parent_path() / idsFile)) << idsFile;
        // Registered well: the atlas covers the tissue as on the straight slices.
        EXPECT_GT(r.quality, 0.8);

        // Ground truth: the landmarks' CCF positions through the registration to the tilted
        // plane, and through the same capture registered to the straight slice instead.
        const fs::path resultDir = (rig_.dir / r.resultPath).parent_path();
        auto capture =
            core::readImage(rig_.dir / rig_.station->journal().capture(r.captureId)->imagePath);
        ASSERT_TRUE(capture);
        const cv::Point2d offset = captureOffset(truth_[std::size_t(i)].slideImage, *capture);
        const double onTilted = medianCcfErrorUm(result, resultDir, truth_[std::size_t(i)], offset);
        RegisterRequest rq;
        auto stack = readStack(work_ / "stack");
        ASSERT_TRUE(stack);
        rq.atlas = *stackSlicePath(*stack, r.atlasSlice);
        rq.image = rig_.dir / rig_.station->journal().capture(r.captureId)->imagePath;
        rq.imageUmPerPx = kUmPerPx;
        rq.atlasUmPerPx = 25;
        rq.atlasSlice = sliceFrame(*stack, r.atlasSlice);
        rq.output = work_ / ("straight-" + std::to_string(i) + ".result.json");
        auto straight = registerSectionFiles(rq);
        ASSERT_TRUE(straight) << straight.error().message;
        const double onStraight =
            medianCcfErrorUm(readJson(rq.output), work_, truth_[std::size_t(i)], offset);
        std::printf("%s landmarks' median CCF error: tilted plane %.0f um, straight slice %.0f um "
                    "(capture at %.0f, %.0f in the slide image)\n",
                    s.name.c_str(), onTilted, onStraight, offset.x, offset.y);
        tiltedErrorUm += onTilted;
        straightErrorUm += onStraight;
    }
    // The search runs once six sections are on the line: the last two at least are tilted.
    EXPECT_GE(tilted, 2);
    // And the tilted planes put the tissue where it truly is in the brain better than the
    // straight slices through the same positions (summed over the tilted sections).
    EXPECT_LT(tiltedErrorUm, straightErrorUm);
}
