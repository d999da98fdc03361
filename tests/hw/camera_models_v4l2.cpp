// V4l2Camera on the emulated device, for the camera conformance suite.
#include "camera_conformance.hpp"
#include "v4l2_emulator.hpp"

#include "slicestation/drivers/v4l2_camera.hpp"

#include <cassert>

namespace slicestation::test {

namespace {
CameraUnderTest makeV4l2(std::vector<std::uint32_t> formats) {
    EmulatedV4l2Options o;
    auto clock = std::make_shared<core::VirtualClock>();
    o.clock = clock;
    o.formats = std::move(formats);
    auto dev = std::make_shared<EmulatedV4l2Device>(o);
    drivers::V4l2CameraConfig c;
    c.device = o.path;
    c.syscalls = dev;
    c.clock = clock;
    auto cam = drivers::V4l2Camera::create(c);
    assert(cam);
    return {dev, std::move(cam).value()};
}
} // namespace

std::vector<CameraModel> cameraModels() {
    return {
        {"V4l2EmulatedAllFormats",
         [] {
             return makeV4l2({V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV,
                              V4L2_PIX_FMT_RGB24, V4L2_PIX_FMT_MJPEG});
         }},
        {"V4l2EmulatedYuyvOnly", [] { return makeV4l2({V4L2_PIX_FMT_YUYV}); }},
        {"V4l2EmulatedMjpegOnly", [] { return makeV4l2({V4L2_PIX_FMT_MJPEG}); }},
    };
}

} // namespace slicestation::test
