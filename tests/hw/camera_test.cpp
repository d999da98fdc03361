// SimCamera physics and FaultyCamera faults (conformance: camera_conformance.cpp).
#include "sim_camera_rig.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <functional>
#include <future>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;
using Rig = SimRig;

Rig makeRig(bool faulty) {
    return makeSimRig(faulty);
}

const cv::Mat& slide() {
    static const cv::Mat s = sim::makeGeneratedSlide(2, {600, 500}, 7).value();
    return s;
}

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
    auto f = sim::FaultyCamera::create(std::move(rig.camera), std::make_shared<core::SteadyClock>())
                 .value();
    f->timeoutNext(1);
    auto* raw = f.get();
    auto fut = std::async(std::launch::async, [raw] { return raw->capture(60s); });
    while (fut.wait_for(10ms) != std::future_status::ready)
        raw->stop();
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
