// Camera conformance for every model, plus SimCamera physics and FaultyCamera faults.
#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <functional>
#include <future>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;

const cv::Mat& slide() {
    static const cv::Mat s = sim::makeGeneratedSlide(2, {600, 500}, 7).value();
    return s;
}

struct Rig {
    std::unique_ptr<sim::SimStage> stage;
    std::unique_ptr<hw::Camera> camera;
    sim::SimCamera* simCamera = nullptr;
};

Rig makeRig(bool faulty) {
    Rig r;
    sim::SimStageConfig sc;
    sc.clock = std::make_shared<core::VirtualClock>();
    sc.limits = {{0, 2400}, {0, 1000}, hw::AxisRange{0, 5000}};
    r.stage = sim::SimStage::create(sc).value();
    sim::SimCameraConfig cc;
    cc.slide = slide();
    auto* st = r.stage.get();
    cc.stagePosition = [st] { return st->peekPosition(); };
    cc.focusTiltX = cc.focusTiltY = 0;
    auto cam = sim::SimCamera::create(cc).value();
    r.simCamera = cam.get();
    if (faulty) r.camera = sim::FaultyCamera::create(std::move(cam), sc.clock).value();
    else r.camera = std::move(cam);
    return r;
}

struct CameraModel {
    std::string name;
    std::function<Rig()> make;
};

class CameraConformance : public ::testing::TestWithParam<CameraModel> {};

TEST_P(CameraConformance, ConfigureReportsWhatIsUsed) {
    auto rig = GetParam().make();
    hw::CameraSettings s;
    s.width = 321; // odd: a model may adjust; the caller reads back
    s.height = 240;
    s.exposureUs = 20'000;
    s.analogueGain = 2.0;
    auto r = rig.camera->configure(s, 1s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_GT(r->width, 0);
    EXPECT_EQ(r->exposureUs, 20'000);
    auto f = rig.camera->capture(1s);
    ASSERT_TRUE(f) << f.error().message;
    EXPECT_EQ(f->width(), r->width);
    EXPECT_EQ(f->height(), r->height);
    EXPECT_EQ(f->metadata.exposureUs, r->exposureUs);
    EXPECT_DOUBLE_EQ(f->metadata.analogueGain, r->analogueGain);
    EXPECT_EQ(f->bytes().size(), f->stride() * static_cast<std::size_t>(f->height()));
}

TEST_P(CameraConformance, EveryFormatAndIncreasingSequence) {
    auto rig = GetParam().make();
    std::uint64_t last = 0;
    bool first = true;
    for (auto fmt : {hw::PixelFormat::Mono8, hw::PixelFormat::Mono16, hw::PixelFormat::Rgb8}) {
        hw::CameraSettings s;
        s.format = fmt;
        s.width = 128;
        s.height = 96;
        ASSERT_TRUE(rig.camera->configure(s, 1s));
        auto f = rig.camera->capture(1s);
        ASSERT_TRUE(f) << f.error().message;
        EXPECT_EQ(f->format(), fmt);
        EXPECT_EQ(f->stride(), static_cast<std::size_t>(128 * hw::bytesPerPixel(fmt)));
        if (!first) {
            EXPECT_GT(f->metadata.sequence, last);
        }
        last = f->metadata.sequence;
        first = false;
    }
}

TEST_P(CameraConformance, BadSettingsAreRejected) {
    auto rig = GetParam().make();
    hw::CameraSettings s;
    s.width = 0;
    auto r = rig.camera->configure(s, 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    s = {};
    s.exposureUs = -1;
    EXPECT_EQ(rig.camera->configure(s, 1s).error().code, ErrorCode::InvalidArgument);
}

TEST_P(CameraConformance, StopIsIdempotent) {
    auto rig = GetParam().make();
    rig.camera->stop();
    rig.camera->stop();
    EXPECT_TRUE(rig.camera->capture(1s));
}

INSTANTIATE_TEST_SUITE_P(AllModels, CameraConformance,
                         ::testing::Values(CameraModel{"SimCamera", [] { return makeRig(false); }},
                                           CameraModel{"FaultyCameraWithoutFaults", [] { return makeRig(true); }}),
                         [](const auto& i) { return i.param.name; });

double sharpness(const hw::Frame& f) {
    cv::Mat m(f.height(), f.width(), CV_8UC1, const_cast<std::uint8_t*>(f.bytes().data()));
    cv::Mat lap;
    cv::Laplacian(m, lap, CV_64F);
    cv::Scalar mean, sd;
    cv::meanStdDev(lap, mean, sd);
    return sd[0];
}

double meanOf(const hw::Frame& f) {
    cv::Mat m(f.height(), f.width(), CV_8UC1, const_cast<std::uint8_t*>(f.bytes().data()));
    return cv::mean(m)[0];
}

TEST(SimCamera, RendersTheSlideUnderTheStage) {
    auto rig = makeRig(false);
    hw::CameraSettings s;
    s.width = 200;
    s.height = 200;
    ASSERT_TRUE(rig.camera->configure(s, 1s));
    ASSERT_TRUE(rig.stage->moveTo({600, 500, 2500}, 10s)); // centre of section 1
    auto tissue = rig.camera->capture(1s).value();
    ASSERT_TRUE(rig.stage->moveTo({10, 10, 2500}, 10s)); // corner: glass
    auto glass = rig.camera->capture(1s).value();
    EXPECT_GT(meanOf(tissue), meanOf(glass) + 5);
    ASSERT_TRUE(tissue.metadata.stage);
    EXPECT_NEAR(tissue.metadata.stage->xUm, 600, 1);
}

TEST(SimCamera, DefocusBlursAndExposureGainBrighten) {
    auto rig = makeRig(false);
    hw::CameraSettings s;
    s.width = 200;
    s.height = 200;
    ASSERT_TRUE(rig.camera->configure(s, 1s));
    ASSERT_TRUE(rig.stage->moveTo({600, 500, 2500}, 10s));
    auto focused = rig.camera->capture(1s).value();
    ASSERT_TRUE(rig.stage->moveTo({600, 500, 2560}, 10s));
    auto blurred = rig.camera->capture(1s).value();
    EXPECT_GT(sharpness(focused), 1.5 * sharpness(blurred));
    ASSERT_TRUE(rig.stage->moveTo({600, 500, 2500}, 10s));
    s.exposureUs = 20'000;
    ASSERT_TRUE(rig.camera->configure(s, 1s));
    auto bright = rig.camera->capture(1s).value();
    EXPECT_GT(meanOf(bright), 1.6 * meanOf(focused));
}

TEST(FaultyCamera, TimeoutsCorruptionAndDisconnect) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto rig = makeRig(false);
    auto f = sim::FaultyCamera::create(std::move(rig.camera), clock).value();
    f->timeoutNext(1);
    EXPECT_EQ(f->capture(500ms).error().code, ErrorCode::Timeout);
    f->corruptNext(1);
    EXPECT_EQ(f->capture(500ms).error().code, ErrorCode::IoError);
    f->disconnectAfter(2);
    EXPECT_TRUE(f->capture(500ms));
    EXPECT_TRUE(f->capture(500ms));
    EXPECT_EQ(f->capture(500ms).error().code, ErrorCode::Disconnected);
    EXPECT_EQ(sim::FaultyCamera::create(nullptr, clock).error().code, ErrorCode::InvalidArgument);
}

TEST(FaultyCamera, StopPreemptsAWait) {
    auto rig = makeRig(false);
    auto f = sim::FaultyCamera::create(std::move(rig.camera), std::make_shared<core::SteadyClock>()).value();
    f->timeoutNext(1);
    auto* raw = f.get();
    auto fut = std::async(std::launch::async, [raw] { return raw->capture(60s); });
    while (fut.wait_for(10ms) != std::future_status::ready) raw->stop();
    EXPECT_EQ(fut.get().error().code, ErrorCode::Cancelled);
}

TEST(SimCamera, CreateRejectsBadConfig) {
    sim::SimCameraConfig cc;
    EXPECT_EQ(sim::SimCamera::create(cc).error().code, ErrorCode::InvalidArgument);
    cc.slide = slide();
    EXPECT_EQ(sim::SimCamera::create(cc).error().code, ErrorCode::InvalidArgument); // no stage
}

} // namespace
} // namespace slicestation::test
