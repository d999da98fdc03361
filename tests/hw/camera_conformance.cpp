// Conformance of every hw::Camera model: the contract written in core/camera.hpp.
#include "camera_conformance.hpp"

#include <gtest/gtest.h>

#include <chrono>

namespace slicestation::test {

using namespace std::chrono_literals;
using core::ErrorCode;

class CameraConformance : public ::testing::TestWithParam<CameraModel> {};

TEST_P(CameraConformance, ConfigureReportsWhatIsUsed) {
    auto cut = GetParam().make();
    hw::CameraSettings s;
    s.width = 321; // odd: a model may adjust; the caller reads back
    s.height = 240;
    s.exposureUs = 20'000;
    s.analogueGain = 2.0;
    auto r = cut.camera->configure(s, 1s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_GT(r->width, 0);
    EXPECT_EQ(r->exposureUs, 20'000);
    auto f = cut.camera->capture(1s);
    ASSERT_TRUE(f) << f.error().message;
    EXPECT_EQ(f->width(), r->width);
    EXPECT_EQ(f->height(), r->height);
    EXPECT_EQ(f->metadata.exposureUs, r->exposureUs);
    EXPECT_DOUBLE_EQ(f->metadata.analogueGain, r->analogueGain);
    EXPECT_EQ(f->bytes().size(), f->stride() * static_cast<std::size_t>(f->height()));
}

TEST_P(CameraConformance, EveryFormatAndIncreasingSequence) {
    auto cut = GetParam().make();
    std::uint64_t last = 0;
    bool first = true;
    for (auto fmt : {hw::PixelFormat::Mono8, hw::PixelFormat::Mono16, hw::PixelFormat::Rgb8}) {
        hw::CameraSettings s;
        s.format = fmt;
        s.width = 128;
        s.height = 96;
        auto r = cut.camera->configure(s, 1s);
        ASSERT_TRUE(r) << r.error().message;
        EXPECT_EQ(r->format, fmt);
        for (int i = 0; i < 2; ++i) {
            auto f = cut.camera->capture(1s);
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
}

TEST_P(CameraConformance, BadSettingsAreRejected) {
    auto cut = GetParam().make();
    hw::CameraSettings s;
    s.width = 0;
    auto r = cut.camera->configure(s, 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    s = {};
    s.exposureUs = -1;
    EXPECT_EQ(cut.camera->configure(s, 1s).error().code, ErrorCode::InvalidArgument);
    s = {};
    s.analogueGain = 0;
    EXPECT_EQ(cut.camera->configure(s, 1s).error().code, ErrorCode::InvalidArgument);
    // A rejected configure leaves the camera usable.
    ASSERT_TRUE(cut.camera->configure(hw::CameraSettings{}, 1s));
    EXPECT_TRUE(cut.camera->capture(1s));
}

TEST_P(CameraConformance, CaptureWithoutConfigureUsesDefaults) {
    auto cut = GetParam().make();
    auto f = cut.camera->capture(1s);
    ASSERT_TRUE(f) << f.error().message;
    EXPECT_FALSE(f->empty());
    EXPECT_GT(f->metadata.exposureUs, 0);
}

TEST_P(CameraConformance, StopIsIdempotentAndDoesNotPoisonTheNextCapture) {
    auto cut = GetParam().make();
    cut.camera->stop();
    cut.camera->stop();
    EXPECT_TRUE(cut.camera->capture(1s));
}

TEST_P(CameraConformance, ZeroTimeoutNeverHangs) {
    auto cut = GetParam().make();
    ASSERT_TRUE(cut.camera->configure(hw::CameraSettings{}, 1s));
    auto f = cut.camera->capture(0ms);
    if (!f) {
        EXPECT_EQ(f.error().code, ErrorCode::Timeout) << f.error().message;
    }
}

INSTANTIATE_TEST_SUITE_P(AllModels, CameraConformance, ::testing::ValuesIn(cameraModels()),
                         [](const auto& i) { return i.param.name; });

} // namespace slicestation::test
