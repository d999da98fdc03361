// LibcameraCamera on a machine without a camera: the no-camera path (capture-apis.md §5.1).
#include "slicestation/drivers/libcamera_camera.hpp"

#include <gtest/gtest.h>

#include <cstdlib>

namespace slicestation::test {
namespace {

using core::ErrorCode;

class LibcameraNoCamera : public ::testing::Test {
protected:
    void SetUp() override {
        ::setenv("LIBCAMERA_LOG_LEVELS", "*:ERROR", 0);
        auto ids = drivers::LibcameraCamera::listCameras();
        ASSERT_TRUE(ids) << ids.error().message;
        if (!ids->empty())
            GTEST_SKIP() << "a camera is attached (" << ids->front()
                         << "): the no-camera path cannot run";
    }
};

TEST_F(LibcameraNoCamera, CreateFailsWithAClearNotFound) {
    auto c = drivers::LibcameraCamera::create({});
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, ErrorCode::NotFound);
    EXPECT_NE(c.error().message.find("no camera found"), std::string::npos) << c.error().message;
}

TEST_F(LibcameraNoCamera, NamedCameraIsNotFoundEither) {
    drivers::LibcameraCameraConfig cfg;
    cfg.cameraId = "/base/soc/i2c0mux/i2c@1/imx477@1a";
    auto c = drivers::LibcameraCamera::create(cfg);
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, ErrorCode::NotFound);
}

TEST_F(LibcameraNoCamera, TheManagerIsReleasedAfterAFailedCreate) {
    for (int i = 0; i < 3; ++i) { // a second CameraManager in one process would abort
        auto c = drivers::LibcameraCamera::create({});
        EXPECT_EQ(c.error().code, ErrorCode::NotFound);
    }
    EXPECT_TRUE(drivers::LibcameraCamera::listCameras());
}

TEST(Libcamera, BadParametersAreInvalidArgument) {
    drivers::LibcameraCameraConfig cfg;
    cfg.bufferCount = 0;
    EXPECT_EQ(drivers::LibcameraCamera::create(cfg).error().code, ErrorCode::InvalidArgument);
}

} // namespace
} // namespace slicestation::test
