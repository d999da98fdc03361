// Autofocus against the simulated stage and camera (tilted focal surface, defocus blur), the
// tissue and focus measures, FocusSurface, and fault pass-through.
#include "slicestation/daemon/station/autofocus.hpp"
#include "slicestation/pipeline/focus_measures.hpp"
#include "slicestation/pipeline/frame_image.hpp"

#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/faulty_stage.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <cmath>
#include <memory>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;

const cv::Mat& slide() {
    // Two generated sections side by side, 1200 x 1000 µm each at 2 µm/px.
    static const cv::Mat s = sim::makeGeneratedSlide(2, {600, 500}, 11).value();
    return s;
}

constexpr double kFocusZ = 2'500;
constexpr double kTiltX = 0.01;
constexpr double kTiltY = -0.004;

double trueFocus(double x, double y) {
    return kFocusZ + kTiltX * x + kTiltY * y;
}

struct Rig {
    std::shared_ptr<core::VirtualClock> clock = std::make_shared<core::VirtualClock>();
    sim::SimStage* simStage = nullptr;
    std::unique_ptr<hw::Stage> stage;
    std::unique_ptr<hw::Camera> camera;
    sim::FaultyStage* faultyStage = nullptr;
    sim::FaultyCamera* faultyCamera = nullptr;
};

Rig makeRig(bool faulty = false, hw::PixelFormat format = hw::PixelFormat::Mono16) {
    Rig r;
    sim::SimStageConfig sc;
    sc.clock = r.clock; // moves "take" time on the virtual clock: instant in the test
    auto stage = sim::SimStage::create(sc).value();
    r.simStage = stage.get();
    sim::SimCameraConfig cc;
    cc.slide = slide();
    cc.slideUmPerPx = 2.0;
    cc.sensorUmPerPx = 2.0;
    cc.focusZUm = kFocusZ;
    cc.focusTiltX = kTiltX;
    cc.focusTiltY = kTiltY;
    auto* st = r.simStage;
    cc.stagePosition = [st] { return st->peekPosition(); };
    auto camera = sim::SimCamera::create(cc).value();
    hw::CameraSettings cs;
    cs.format = format;
    cs.width = 320; // 640 x 480 µm field: small frames keep the test fast
    cs.height = 240;
    EXPECT_TRUE(camera->configure(cs, 1s));
    if (faulty) {
        auto fs = sim::FaultyStage::create(std::move(stage), r.clock).value();
        auto fc = sim::FaultyCamera::create(std::move(camera), r.clock).value();
        r.faultyStage = fs.get();
        r.faultyCamera = fc.get();
        r.stage = std::move(fs);
        r.camera = std::move(fc);
    } else {
        r.stage = std::move(stage);
        r.camera = std::move(camera);
    }
    return r;
}

cv::Mat captureAt(Rig& rig, const hw::StagePosition& p) {
    EXPECT_TRUE(rig.stage->moveTo(p, 10s));
    auto frame = rig.camera->capture(1s);
    EXPECT_TRUE(frame);
    return frame ? pipeline::frameToMat(*frame) : cv::Mat();
}

TEST(FrameToMat, CopiesInOpenCvConventions) {
    hw::Frame rgb(hw::PixelFormat::Rgb8, 3, 2);
    rgb.row(1)[3] = 10; // pixel (1, 1): R
    rgb.row(1)[5] = 30; //               B
    cv::Mat m = pipeline::frameToMat(rgb);
    ASSERT_EQ(m.type(), CV_8UC3);
    EXPECT_EQ(m.at<cv::Vec3b>(1, 1), cv::Vec3b(30, 0, 10)); // BGR
    rgb.row(1)[3] = 99;
    EXPECT_EQ(m.at<cv::Vec3b>(1, 1)[2], 10) << "a deep copy";

    hw::Frame mono16(hw::PixelFormat::Mono16, 4, 3);
    reinterpret_cast<std::uint16_t*>(mono16.row(2))[3] = 60'000;
    m = pipeline::frameToMat(mono16);
    ASSERT_EQ(m.type(), CV_16UC1);
    EXPECT_EQ(m.at<std::uint16_t>(2, 3), 60'000);
    EXPECT_EQ(pipeline::frameToMat(hw::Frame(hw::PixelFormat::Mono8, 5, 4)).type(), CV_8UC1);
    EXPECT_TRUE(pipeline::frameToMat(hw::Frame()).empty());
}

TEST(TissueFraction, TissueGlassAndBrightfield) {
    Rig rig = makeRig();
    const cv::Mat tissue = captureAt(rig, {600, 500, trueFocus(600, 500)});
    const cv::Mat blurred = captureAt(rig, {600, 500, trueFocus(600, 500) + 80});
    const cv::Mat glass = captureAt(rig, {5'000, 500, trueFocus(5'000, 500)});
    const cv::Mat glassBlurred = captureAt(rig, {5'000, 500, trueFocus(5'000, 500) - 70});
    EXPECT_GT(pipeline::tissueFraction(tissue), 0.3);
    EXPECT_GT(pipeline::tissueFraction(blurred), 0.3) << "defocus must not hide the tissue";
    EXPECT_LT(pipeline::tissueFraction(glass), 0.005);
    EXPECT_LT(pipeline::tissueFraction(glassBlurred), 0.005);

    // Brightfield: dark tissue on bright glass (the same field inverted), 8-bit colour.
    cv::Mat inverted;
    cv::subtract(cv::Scalar::all(65535), tissue, inverted);
    cv::Mat bgr;
    inverted.convertTo(bgr, CV_8U, 1.0 / 257);
    cv::cvtColor(bgr, bgr, cv::COLOR_GRAY2BGR);
    EXPECT_NEAR(pipeline::tissueFraction(bgr), pipeline::tissueFraction(tissue), 0.05);
    cv::Mat brightGlass;
    cv::subtract(cv::Scalar::all(65535), glass, brightGlass);
    EXPECT_LT(pipeline::tissueFraction(brightGlass), 0.005);
    EXPECT_EQ(pipeline::tissueFraction(cv::Mat()), 0.0);
}

TEST(FocusMeasure, PeaksAtFocusAndIgnoresBrightness) {
    Rig rig = makeRig();
    const double z0 = trueFocus(600, 500);
    double previous = 1e300;
    for (const double dz : {0.0, 5.0, 15.0, 40.0}) {
        const double score = pipeline::focusMeasure(captureAt(rig, {600, 500, z0 + dz}));
        EXPECT_LT(score, previous) << "dz " << dz;
        previous = score;
    }
    const cv::Mat sharp = captureAt(rig, {600, 500, z0});
    cv::Mat dimmer;
    sharp.convertTo(dimmer, CV_16U, 0.5);
    EXPECT_NEAR(pipeline::focusMeasure(dimmer), pipeline::focusMeasure(sharp),
                0.02 * pipeline::focusMeasure(sharp));
    EXPECT_EQ(pipeline::focusMeasure(cv::Mat()), 0.0);
    EXPECT_EQ(pipeline::focusMeasure(cv::Mat(10, 10, CV_8UC1, cv::Scalar(0))), 0.0);
}

struct Place {
    double x, y, startOffset;
};

class AutofocusAccuracy : public ::testing::TestWithParam<Place> {};

TEST_P(AutofocusAccuracy, FindsTheFocalSurfaceWithinAFineStep) {
    Rig rig = makeRig();
    const Place p = GetParam();
    const double truth = trueFocus(p.x, p.y);
    daemon::AutofocusSettings s;
    auto r = daemon::autofocus(*rig.stage, *rig.camera, {p.x, p.y, truth + p.startOffset}, s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_TRUE(r->tissueFound);
    EXPECT_NEAR(r->zUm, truth, s.fineStepUm) << "start offset " << p.startOffset;
    RecordProperty("focus_error_um", std::to_string(r->zUm - truth));
    EXPECT_FALSE(r->peakAtRangeEdge);
    EXPECT_GT(r->score, 0);
    EXPECT_LE(r->captures, 1 + 7 + 11);
    // The stage is left at the focus found.
    EXPECT_NEAR(rig.simStage->peekPosition().zUm, r->zUm, 1.0);
}

INSTANTIATE_TEST_SUITE_P(Sections, AutofocusAccuracy,
                         ::testing::Values(Place{600, 500, 0}, Place{600, 500, 40},
                                           Place{700, 450, -55}, Place{1800, 500, 30},
                                           Place{1750, 600, -12}));

TEST(Autofocus, BlankGlassIsNotSearched) {
    Rig rig = makeRig();
    const double start = 2'530;
    auto r = daemon::autofocus(*rig.stage, *rig.camera, {5'000, 500, start}, {});
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_FALSE(r->tissueFound);
    EXPECT_EQ(r->zUm, start);
    EXPECT_LE(r->captures, 2);
    EXPECT_LT(r->tissueFraction, 0.03);
    EXPECT_EQ(rig.simStage->peekPosition().zUm, start);
}

TEST(Autofocus, PeakBeyondTheRangeIsFlagged) {
    Rig rig = makeRig();
    const double truth = trueFocus(600, 500);
    auto r = daemon::autofocus(*rig.stage, *rig.camera, {600, 500, truth - 200}, {});
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_TRUE(r->tissueFound);
    EXPECT_TRUE(r->peakAtRangeEdge);
}

TEST(Autofocus, InvalidSettings) {
    Rig rig = makeRig();
    const hw::StagePosition at{600, 500, 2'500};
    const auto expectInvalid = [&](daemon::AutofocusSettings s, const char* why) {
        auto r = daemon::autofocus(*rig.stage, *rig.camera, at, s);
        ASSERT_FALSE(r) << why;
        EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument) << why;
    };
    daemon::AutofocusSettings s;
    s.coarseStepUm = 0;
    expectInvalid(s, "coarse step");
    s = {};
    s.fineStepUm = -1;
    expectInvalid(s, "fine step");
    s = {};
    s.fineStepUm = 30;
    expectInvalid(s, "fine > coarse");
    s = {};
    s.rangeUm = 10;
    expectInvalid(s, "range < coarse");
    s = {};
    s.minTissueFraction = 1.5;
    expectInvalid(s, "tissue fraction");
    s = {};
    s.moveTimeout = 0ms;
    expectInvalid(s, "timeout");
}

TEST(Autofocus, StageWithoutZIsInvalid) {
    auto clock = std::make_shared<core::VirtualClock>();
    sim::SimStageConfig sc;
    sc.clock = clock;
    sc.limits.z.reset();
    auto stage = sim::SimStage::create(sc).value();
    Rig rig = makeRig();
    auto r = daemon::autofocus(*stage, *rig.camera, {600, 500, 0}, {});
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
}

TEST(Autofocus, StageErrorsComeBackUnchanged) {
    Rig rig = makeRig(true);
    const hw::StagePosition at{600, 500, trueFocus(600, 500)};
    rig.faultyStage->failNext(sim::FaultyStage::Op::Move,
                              core::makeError(ErrorCode::Alarm, "z drive alarm 0x42"));
    auto alarm = daemon::autofocus(*rig.stage, *rig.camera, at, {});
    ASSERT_FALSE(alarm);
    EXPECT_EQ(alarm.error().code, ErrorCode::Alarm);
    EXPECT_EQ(alarm.error().message, "z drive alarm 0x42");

    rig.faultyStage->stallMoves(true); // a move that never settles
    auto stalled = daemon::autofocus(*rig.stage, *rig.camera, at, {});
    ASSERT_FALSE(stalled);
    EXPECT_EQ(stalled.error().code, ErrorCode::Timeout);
    rig.faultyStage->stallMoves(false);

    auto outside = daemon::autofocus(*rig.stage, *rig.camera, {600, 500, 99'999}, {});
    ASSERT_FALSE(outside);
    EXPECT_EQ(outside.error().code, ErrorCode::OutOfRange);
}

TEST(Autofocus, CameraErrorsComeBackUnchanged) {
    Rig rig = makeRig(true);
    const hw::StagePosition at{600, 500, trueFocus(600, 500)};
    rig.faultyCamera->timeoutNext(1);
    auto timeout = daemon::autofocus(*rig.stage, *rig.camera, at, {});
    ASSERT_FALSE(timeout);
    EXPECT_EQ(timeout.error().code, ErrorCode::Timeout);

    rig.faultyCamera->corruptNext(1);
    auto corrupt = daemon::autofocus(*rig.stage, *rig.camera, at, {});
    ASSERT_FALSE(corrupt);
    EXPECT_EQ(corrupt.error().code, ErrorCode::IoError);

    rig.faultyCamera->disconnectAfter(4); // mid-sweep
    auto gone = daemon::autofocus(*rig.stage, *rig.camera, at, {});
    ASSERT_FALSE(gone);
    EXPECT_EQ(gone.error().code, ErrorCode::Disconnected);
}

TEST(FocusSurface, RecoversAKnownPlane) {
    daemon::FocusSurface surface;
    EXPECT_FALSE(surface.predict(0, 0));
    surface.add(1'000, 2'000, trueFocus(1'000, 2'000));
    EXPECT_EQ(surface.size(), 1u);
    EXPECT_DOUBLE_EQ(*surface.predict(50'000, 9'000), trueFocus(1'000, 2'000)); // the mean
    surface.add(3'000, 2'000, trueFocus(3'000, 2'000));
    EXPECT_DOUBLE_EQ(*surface.predict(0, 0),
                     (trueFocus(1'000, 2'000) + trueFocus(3'000, 2'000)) / 2);
    // Three in a row (sections side by side): the tilt along the row is used.
    surface.add(5'000, 2'000, trueFocus(5'000, 2'000));
    EXPECT_NEAR(*surface.predict(9'000, 2'000), trueFocus(9'000, 2'000), 1e-6);
    // Off the line, then a full plane.
    surface.add(2'000, 12'000, trueFocus(2'000, 12'000));
    for (const auto& [x, y] : {std::pair{0.0, 0.0}, {40'000.0, 20'000.0}, {7'000.0, 15'000.0}}) {
        EXPECT_NEAR(*surface.predict(x, y), trueFocus(x, y), 1e-6) << x << ", " << y;
    }
    // Noisy measurements: least squares, not interpolation.
    daemon::FocusSurface noisy;
    cv::RNG rng(5);
    for (int i = 0; i < 40; ++i) {
        const double x = rng.uniform(0.0, 70'000.0), y = rng.uniform(0.0, 25'000.0);
        noisy.add(x, y, trueFocus(x, y) + rng.gaussian(2.0));
    }
    EXPECT_NEAR(*noisy.predict(35'000, 12'000), trueFocus(35'000, 12'000), 1.5);
    surface.clear();
    EXPECT_EQ(surface.size(), 0u);
    // All at one place: the mean.
    daemon::FocusSurface same;
    for (double z : {10.0, 20.0, 30.0})
        same.add(5, 5, z);
    EXPECT_DOUBLE_EQ(*same.predict(100, 100), 20.0);
}

TEST(FocusSurface, StartsTheNextSearchClose) {
    Rig rig = makeRig();
    daemon::FocusSurface surface;
    daemon::AutofocusSettings s;
    for (const auto& [x, y] : {std::pair{500.0, 450.0}, {1'700.0, 520.0}, {600.0, 650.0}}) {
        const double start = surface.predict(x, y).value_or(kFocusZ);
        auto r = daemon::autofocus(*rig.stage, *rig.camera, {x, y, start}, s);
        ASSERT_TRUE(r && r->tissueFound);
        surface.add(x, y, r->zUm);
    }
    EXPECT_NEAR(*surface.predict(1'800, 600), trueFocus(1'800, 600), 2 * s.fineStepUm);
}

} // namespace

TEST(Autofocus, TellsWhichDeviceFailed) {
    Rig rig = makeRig(true);
    const hw::StagePosition at{600, 500, trueFocus(600, 500)};
    daemon::FocusFailure failed = daemon::FocusFailure::Camera;
    rig.faultyStage->disconnectAfter(3); // mid-sweep
    auto gone = daemon::autofocus(*rig.stage, *rig.camera, at, {}, &failed);
    ASSERT_FALSE(gone);
    EXPECT_EQ(gone.error().code, ErrorCode::Disconnected);
    EXPECT_EQ(failed, daemon::FocusFailure::Stage);
    rig.faultyStage->disconnectAfter(-1);

    rig.faultyStage->stallMoves(true);
    daemon::AutofocusSettings quick;
    quick.moveTimeout = std::chrono::milliseconds(50);
    auto stalled = daemon::autofocus(*rig.stage, *rig.camera, at, quick, &failed);
    ASSERT_FALSE(stalled);
    EXPECT_EQ(stalled.error().code, ErrorCode::Timeout);
    EXPECT_EQ(failed, daemon::FocusFailure::Stage) << "a move that timed out is the stage's";
    rig.faultyStage->stallMoves(false);

    rig.faultyCamera->timeoutNext(1);
    auto timeout = daemon::autofocus(*rig.stage, *rig.camera, at, {}, &failed);
    ASSERT_FALSE(timeout);
    EXPECT_EQ(timeout.error().code, ErrorCode::Timeout);
    EXPECT_EQ(failed, daemon::FocusFailure::Camera) << "a capture that timed out is the camera's";

    daemon::AutofocusSettings bad;
    bad.fineStepUm = 0;
    auto invalid = daemon::autofocus(*rig.stage, *rig.camera, at, bad, &failed);
    ASSERT_FALSE(invalid);
    EXPECT_EQ(failed, daemon::FocusFailure::Focus);
}

} // namespace slicestation::test
