// V4l2Camera against the emulated device: negotiation, controls, buffers, conversions, faults.
// Every error code the driver returns is provoked here.
#include "v4l2_emulator.hpp"

#include "slicestation/drivers/v4l2_camera.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;

struct Bench {
    std::shared_ptr<core::VirtualClock> clock = std::make_shared<core::VirtualClock>();
    std::shared_ptr<EmulatedV4l2Device> dev;
    drivers::V4l2CameraConfig config;
    explicit Bench(EmulatedV4l2Options o = {}) {
        o.clock = clock;
        dev = std::make_shared<EmulatedV4l2Device>(o);
        config.device = o.path;
        config.syscalls = dev;
        config.clock = clock;
        config.settleFrames = 0;
        config.staleFrames = 0;
    }
    core::Result<std::unique_ptr<drivers::V4l2Camera>> create() {
        return drivers::V4l2Camera::create(config);
    }
    std::unique_ptr<drivers::V4l2Camera> camera() {
        auto c = create();
        EXPECT_TRUE(c) << c.error().message;
        return std::move(c).value();
    }
};

EmulatedV4l2Options only(std::uint32_t fcc) {
    EmulatedV4l2Options o;
    o.formats = {fcc};
    return o;
}

hw::CameraSettings settings(hw::PixelFormat f = hw::PixelFormat::Mono8, int w = 64, int h = 48) {
    hw::CameraSettings s;
    s.format = f;
    s.width = w;
    s.height = h;
    return s;
}

// ---- create ---------------------------------------------------------------------------------

TEST(V4l2Create, MissingDeviceIsNotFound) {
    Bench b;
    b.config.device = "/dev/video-none";
    auto c = b.create();
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, ErrorCode::NotFound);
    EXPECT_NE(c.error().message.find("/dev/video-none"), std::string::npos);
    EXPECT_EQ(c.error().sysErrno, ENOENT);
}

TEST(V4l2Create, PermissionDeniedIsIoErrorWithErrno) {
    Bench b;
    b.dev->failOpen(EACCES);
    auto c = b.create();
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, ErrorCode::IoError);
    EXPECT_EQ(c.error().sysErrno, EACCES);
}

TEST(V4l2Create, CapabilitiesAreChecked) {
    for (std::uint32_t caps : {std::uint32_t{V4L2_CAP_VIDEO_OUTPUT | V4L2_CAP_STREAMING},
                               std::uint32_t{V4L2_CAP_VIDEO_CAPTURE_MPLANE | V4L2_CAP_STREAMING},
                               std::uint32_t{V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_READWRITE}}) {
        EmulatedV4l2Options o;
        o.deviceCaps = caps;
        Bench b(o);
        auto c = b.create();
        ASSERT_FALSE(c);
        EXPECT_EQ(c.error().code, ErrorCode::Unsupported) << c.error().message;
        EXPECT_EQ(b.dev->openFds(), 0) << "the fd is closed on failure";
    }
}

TEST(V4l2Create, NotAV4l2DeviceAndQuerycapFailure) {
    Bench b;
    b.dev->failIoctl(VIDIOC_QUERYCAP, ENOTTY);
    EXPECT_EQ(b.create().error().code, ErrorCode::Unsupported);
    b.dev->failIoctl(VIDIOC_QUERYCAP, EIO);
    EXPECT_EQ(b.create().error().code, ErrorCode::IoError);
}

TEST(V4l2Create, BadParametersAreInvalidArgument) {
    Bench b;
    b.config.bufferCount = 0;
    EXPECT_EQ(b.create().error().code, ErrorCode::InvalidArgument);
    Bench e;
    e.config.device.clear();
    EXPECT_EQ(e.create().error().code, ErrorCode::InvalidArgument);
}

// ---- configure ------------------------------------------------------------------------------

TEST(V4l2Configure, AcceptsWhatTheDriverAdjusts) {
    EmulatedV4l2Options o;
    o.linePaddingBytes = 16; // padded lines must not shear the image
    Bench b(o);
    auto cam = b.camera();
    auto r = cam->configure(settings(hw::PixelFormat::Mono8, 1921, 1081), 1s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_EQ(r->width, 1280);
    EXPECT_EQ(r->height, 720);
    EXPECT_EQ(cam->negotiatedFourcc(), "GREY");
    auto f = cam->capture(1s);
    ASSERT_TRUE(f) << f.error().message;
    ASSERT_EQ(f->width(), 1280);
    const auto seq = static_cast<std::uint32_t>(b.dev->framesProduced() - 1);
    for (int y : {0, 1, 719})
        for (int x : {0, 5, 1279})
            EXPECT_EQ(f->row(y)[x], EmulatedV4l2Device::pattern(x, y, seq)) << x << "," << y;
}

TEST(V4l2Configure, ManualExposureGainAndWhiteBalanceAreSetAndReadBack) {
    Bench b;
    auto cam = b.camera();
    hw::CameraSettings s = settings(hw::PixelFormat::Rgb8);
    s.exposureUs = 12'345; // V4L2 exposure is in 100 µs steps: 12'300 in force
    s.analogueGain = 2.5;
    s.redGain = 1.5;
    s.blueGain = 0.8;
    auto r = cam->configure(s, 1s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_EQ(b.dev->control(V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL);
    EXPECT_EQ(b.dev->control(V4L2_CID_EXPOSURE_ABSOLUTE), 123);
    EXPECT_EQ(b.dev->control(V4L2_CID_AUTO_WHITE_BALANCE), 0);
    EXPECT_EQ(r->exposureUs, 12'300);
    EXPECT_DOUBLE_EQ(r->analogueGain, 2.5);
    EXPECT_DOUBLE_EQ(r->redGain, 1.5);
    EXPECT_DOUBLE_EQ(r->blueGain, 0.8);
    // The device clamps silently: the clamped value is reported.
    s.analogueGain = 50; // 5000 units, emulator max 1000
    r = cam->configure(s, 1s);
    ASSERT_TRUE(r);
    EXPECT_DOUBLE_EQ(r->analogueGain, 10.0);
    auto f = cam->capture(1s).value();
    EXPECT_DOUBLE_EQ(f.metadata.analogueGain, 10.0);
    EXPECT_EQ(f.metadata.exposureUs, 12'300);
}

TEST(V4l2Configure, OutOfRangeControlIsInvalidArgument) {
    EmulatedV4l2Options o;
    o.rangeErrors = true;
    Bench b(o);
    auto cam = b.camera();
    hw::CameraSettings s = settings();
    s.exposureUs = 2'000'000; // 20000 units > 10000
    auto r = cam->configure(s, 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(r.error().message.find("exposure_time_absolute"), std::string::npos);
}

TEST(V4l2Configure, MissingControlsAreUnsupported) {
    {
        EmulatedV4l2Options o;
        o.hasExposure = false;
        Bench b(o);
        auto r = b.camera()->configure(settings(), 1s);
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, ErrorCode::Unsupported);
    }
    {
        EmulatedV4l2Options o;
        o.hasGain = false;
        Bench b(o);
        auto cam = b.camera();
        EXPECT_TRUE(cam->configure(settings(), 1s)) << "gain 1 needs no control";
        auto s = settings();
        s.analogueGain = 2;
        EXPECT_EQ(cam->configure(s, 1s).error().code, ErrorCode::Unsupported);
    }
    {
        EmulatedV4l2Options o;
        o.hasWhiteBalance = false;
        Bench b(o);
        auto cam = b.camera();
        auto s = settings(hw::PixelFormat::Rgb8);
        s.redGain = 2;
        EXPECT_EQ(cam->configure(s, 1s).error().code, ErrorCode::Unsupported);
    }
}

TEST(V4l2Configure, NoDecodableFormatIsUnsupported) {
    Bench b(only(V4L2_PIX_FMT_NV12));
    auto r = b.camera()->configure(settings(), 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Unsupported);
}

TEST(V4l2Configure, IoctlAndMmapFailures) {
    struct Case {
        unsigned long request;
        int err;
        ErrorCode code;
    };
    for (const Case& c : {Case{VIDIOC_S_FMT, EBUSY, ErrorCode::IoError},
                          Case{VIDIOC_S_CTRL, EIO, ErrorCode::IoError},
                          Case{VIDIOC_G_CTRL, EIO, ErrorCode::IoError},
                          Case{VIDIOC_REQBUFS, ENOMEM, ErrorCode::IoError},
                          Case{VIDIOC_REQBUFS, EINVAL, ErrorCode::Unsupported},
                          Case{VIDIOC_QUERYBUF, EINVAL, ErrorCode::IoError},
                          Case{VIDIOC_QBUF, EIO, ErrorCode::IoError},
                          Case{VIDIOC_STREAMON, EIO, ErrorCode::IoError},
                          Case{VIDIOC_S_FMT, ENODEV, ErrorCode::Disconnected}}) {
        Bench b;
        auto cam = b.camera();
        b.dev->failIoctl(c.request, c.err);
        auto r = cam->configure(settings(), 1s);
        ASSERT_FALSE(r) << c.request;
        EXPECT_EQ(r.error().code, c.code) << r.error().message;
        EXPECT_EQ(r.error().sysErrno, c.err);
        EXPECT_EQ(b.dev->mappedBuffers(), 0) << "nothing left mapped after a failed configure";
        // The camera recovers on the next configure.
        ASSERT_TRUE(cam->configure(settings(), 1s)) << r.error().message;
        EXPECT_TRUE(cam->capture(1s));
    }
    Bench m;
    auto cam = m.camera();
    m.dev->failMmap();
    auto r = cam->configure(settings(), 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_EQ(r.error().sysErrno, ENOMEM);
    m.dev->grantBuffers(0);
    r = cam->configure(settings(), 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_NE(r.error().message.find("no buffers"), std::string::npos);
    m.dev->grantBuffers(1); // fewer than asked is fine
    ASSERT_TRUE(cam->configure(settings(), 1s));
    EXPECT_TRUE(cam->capture(1s));
    EXPECT_TRUE(cam->capture(1s));
}

// ---- conversions ----------------------------------------------------------------------------

struct ConversionCase {
    std::uint32_t fourcc;
    hw::PixelFormat target;
    int tolerance; // MJPEG is lossy
};

class V4l2Conversion : public ::testing::TestWithParam<ConversionCase> {};

TEST_P(V4l2Conversion, PixelsMatchThePattern) {
    const auto c = GetParam();
    Bench b(only(c.fourcc));
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(c.target, 96, 64), 1s));
    auto f = cam->capture(1s);
    ASSERT_TRUE(f) << f.error().message;
    ASSERT_EQ(f->format(), c.target);
    const auto seq = static_cast<std::uint32_t>(b.dev->framesProduced() - 1);
    int worst = 0;
    for (int y = 0; y < 64; y += 7)
        for (int x = 0; x < 96; x += 5) {
            int want = EmulatedV4l2Device::pattern(x, y, seq);
            if (c.fourcc == V4L2_PIX_FMT_YUYV &&
                c.target == hw::PixelFormat::Rgb8) // BT.601 limited range
                want =
                    std::clamp(static_cast<int>(std::lround((want - 16) * 255.0 / 219.0)), 0, 255);
            int got = 0;
            const std::uint8_t* row = f->row(y);
            switch (c.target) {
            case hw::PixelFormat::Mono8:
                got = row[x];
                break;
            case hw::PixelFormat::Mono16: {
                std::uint16_t v;
                std::memcpy(&v, row + 2 * x, 2);
                got = v >> 8;
                break;
            }
            case hw::PixelFormat::Rgb8:
                got = row[3 * x + 1];
                EXPECT_NEAR(row[3 * x], row[3 * x + 2], 2 + c.tolerance) << "grey stays grey";
                break;
            }
            worst = std::max(worst, std::abs(got - want));
        }
    EXPECT_LE(worst, c.tolerance);
}

std::vector<ConversionCase> conversionCases() {
    std::vector<ConversionCase> v;
    for (auto fcc : {V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_RGB24,
                     V4L2_PIX_FMT_MJPEG})
        for (auto t : {hw::PixelFormat::Mono8, hw::PixelFormat::Mono16, hw::PixelFormat::Rgb8}) {
            int tol = fcc == V4L2_PIX_FMT_MJPEG ? 4 : 0;
            if (fcc == V4L2_PIX_FMT_YUYV && t == hw::PixelFormat::Rgb8)
                tol = 3; // limited-range YUV
            v.push_back({fcc, t, tol});
        }
    return v;
}

INSTANTIATE_TEST_SUITE_P(AllPairs, V4l2Conversion, ::testing::ValuesIn(conversionCases()),
                         [](const auto& i) {
                             std::string n;
                             for (int k = 0; k < 4; ++k) {
                                 const char ch =
                                     static_cast<char>((i.param.fourcc >> (8 * k)) & 0xff);
                                 if (std::isalnum(static_cast<unsigned char>(ch)))
                                     n += ch;
                             }
                             return n + "_to_" + hw::toString(i.param.target);
                         });

// ---- capture --------------------------------------------------------------------------------

TEST(V4l2Capture, SettleAndStaleFramesAreDropped) {
    Bench b;
    b.config.settleFrames = 3;
    b.config.staleFrames = 1;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    auto f = cam->capture(1s).value();
    EXPECT_EQ(b.dev->framesProduced(), 5u) << "3 settle + 1 stale dropped, the 5th kept";
    auto g = cam->capture(1s).value();
    EXPECT_EQ(b.dev->framesProduced(), 7u) << "only the stale frame is dropped now";
    EXPECT_GT(g.metadata.sequence, f.metadata.sequence);
    EXPECT_GT(g.metadata.timestampNs, f.metadata.timestampNs);
}

TEST(V4l2Capture, TimeoutWhenNoFrameComes) {
    Bench b;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    b.dev->timeoutPolls(1'000'000);
    const auto t0 = b.clock->now();
    auto f = cam->capture(2s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::Timeout);
    EXPECT_GE(b.clock->now() - t0, 2s);
    EXPECT_LT(b.clock->now() - t0, 2s + 200ms) << "the deadline is kept";
    b.dev->timeoutPolls(0);
    EXPECT_TRUE(cam->capture(1s)) << "the next capture works";
}

TEST(V4l2Capture, CorruptBuffersAreIoErrorAndRequeued) {
    for (Corruption k : {Corruption::ShortBytesUsed, Corruption::ErrorFlag, Corruption::BadIndex}) {
        Bench b;
        auto cam = b.camera();
        ASSERT_TRUE(cam->configure(settings(), 1s));
        b.dev->corruptNext(k);
        auto f = cam->capture(1s);
        ASSERT_FALSE(f);
        EXPECT_EQ(f.error().code, ErrorCode::IoError);
        EXPECT_NE(f.error().message.find("frame"), std::string::npos) << f.error().message;
        for (int i = 0; i < 6; ++i)
            EXPECT_TRUE(cam->capture(1s)) << "buffers still cycle, " << i;
    }
    Bench j(only(V4L2_PIX_FMT_MJPEG));
    auto cam = j.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    j.dev->corruptNext(Corruption::GarbageJpeg);
    auto f = cam->capture(1s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::IoError);
    j.dev->corruptNext(Corruption::ShortBytesUsed); // bytesused 0
    EXPECT_EQ(cam->capture(1s).error().code, ErrorCode::IoError);
    // A frame claiming 30000 x 30000 px is refused from its header, before the decoder would
    // allocate 900 MB for it.
    j.dev->corruptNext(Corruption::JpegClaimsHugeSize);
    f = cam->capture(1s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::IoError);
    EXPECT_NE(f.error().message.find("claims 30000x30000"), std::string::npos) << f.error().message;
    EXPECT_TRUE(cam->capture(1s));
}

TEST(V4l2Capture, DqbufAndPollFailures) {
    Bench b;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    b.dev->failIoctl(VIDIOC_DQBUF, EIO);
    auto f = cam->capture(1s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::IoError);
    EXPECT_EQ(f.error().sysErrno, EIO);
    b.dev->failPoll(EBADF);
    EXPECT_EQ(cam->capture(1s).error().code, ErrorCode::IoError);
    b.dev->failPoll(EINTR); // retried
    EXPECT_TRUE(cam->capture(1s));
}

TEST(V4l2Capture, UnplugIsAFullReinitialisation) {
    Bench b;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(hw::PixelFormat::Mono8, 320, 240), 1s));
    ASSERT_TRUE(cam->capture(1s));
    const int opensBefore = b.dev->opens();
    b.dev->unplug(2); // gone for two open attempts
    auto f = cam->capture(5s);
    ASSERT_TRUE(f) << f.error().message;
    EXPECT_EQ(f->width(), 320) << "the same format is negotiated again";
    EXPECT_EQ(cam->reinitCount(), 1);
    EXPECT_EQ(b.dev->opens() - opensBefore, 3);
    EXPECT_EQ(b.dev->openFds(), 1) << "the stale fd was closed";
    EXPECT_EQ(b.dev->control(V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL)
        << "controls re-applied";
}

TEST(V4l2Capture, UnplugAfterFramesAndEnodevFromDqbuf) {
    Bench b;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    b.dev->unplugAfterFrames(2, 0);
    for (int i = 0; i < 4; ++i)
        ASSERT_TRUE(cam->capture(5s)) << i;
    EXPECT_EQ(cam->reinitCount(), 1);
    b.dev->failIoctl(VIDIOC_DQBUF, ENODEV);
    ASSERT_TRUE(cam->capture(5s));
    EXPECT_EQ(cam->reinitCount(), 2);
}

TEST(V4l2Capture, GoneForGoodIsDisconnectedAfterBoundedAttempts) {
    Bench b;
    b.config.maxReinitAttempts = 3;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    const int opensBefore = b.dev->opens();
    b.dev->unplug(1'000'000);
    auto f = cam->capture(60s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::Disconnected);
    EXPECT_EQ(b.dev->opens() - opensBefore, 3);
    EXPECT_EQ(b.dev->openFds(), 0);
    EXPECT_EQ(b.dev->mappedBuffers(), 0);
    // Later captures try again (bounded each time); once the device is back they work.
    EXPECT_EQ(cam->capture(60s).error().code, ErrorCode::Disconnected);
    b.dev->unplug(0);
    EXPECT_TRUE(cam->capture(5s));
}

TEST(V4l2Capture, ReinitStopsAtTheDeadline) {
    Bench b;
    b.config.maxReinitAttempts = 100;
    b.config.reinitDelay = 500ms;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    b.dev->unplug(1'000'000);
    const int opensBefore = b.dev->opens();
    auto f = cam->capture(1200ms);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::Disconnected);
    EXPECT_LE(b.dev->opens() - opensBefore, 4);
}

TEST(V4l2Capture, StopPreemptsAWaitAndAReinitialisation) {
    Bench b;
    auto cam = b.camera();
    ASSERT_TRUE(cam->configure(settings(), 1s));
    auto* raw = cam.get();
    int polls = 0;
    b.dev->onPoll([&] {
        if (++polls == 3)
            raw->stop(); // as if from another thread, mid-wait
    });
    b.dev->timeoutPolls(1'000'000);
    auto f = cam->capture(3600s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::Cancelled);
    EXPECT_LE(polls, 4);
    b.dev->timeoutPolls(0);
    b.dev->onPoll(nullptr);
    EXPECT_TRUE(cam->capture(1s)) << "stop does not poison the next capture";

    polls = 0;
    b.dev->onPoll([&] { raw->stop(); });
    b.dev->unplugAfterFrames(0, 1'000'000); // unplugged during the wait
    f = cam->capture(3600s);
    ASSERT_FALSE(f);
    EXPECT_EQ(f.error().code, ErrorCode::Cancelled);
}

TEST(V4l2Capture, NothingLeaksOverALifetime) {
    Bench b;
    {
        auto cam = b.camera();
        ASSERT_TRUE(cam->configure(settings(), 1s));
        ASSERT_TRUE(cam->capture(1s));
        ASSERT_TRUE(cam->configure(settings(hw::PixelFormat::Rgb8), 1s));
        b.dev->unplug(1);
        ASSERT_TRUE(cam->capture(5s));
        EXPECT_EQ(b.dev->openFds(), 1);
    }
    EXPECT_EQ(b.dev->openFds(), 0);
    EXPECT_EQ(b.dev->mappedBuffers(), 0);
    EXPECT_FALSE(b.dev->streaming());
}

} // namespace
} // namespace slicestation::test
