// The libcamera driver is loaded when used (libcamera_camera.hpp, "Loading"): this program
// links only the drivers' library, so libcamera is not in the process until the first call,
// and the call through the loaded module takes the same no-camera path as the driver itself.
#include "slicestation/drivers/libcamera_camera.hpp"

#include <gtest/gtest.h>

#include <cstdlib>
#include <fstream>
#include <string>

namespace slicestation::test {
namespace {

using core::ErrorCode;

/// Whether a file whose name begins with `name` is mapped into this process ("libcamera.so"
/// is libcamera itself, not the driver module libslst_libcamera.so).
bool mapped(const std::string& name) {
    std::ifstream maps("/proc/self/maps");
    std::string line;
    while (std::getline(maps, line))
        if (line.find("/" + name) != std::string::npos)
            return true;
    return false;
}

// Run in a forked child (so that this process has not loaded the module yet for the next test):
// with SLICESTATION_DRIVER_DIR naming a folder without the module, only that folder is tried.
TEST(LibcameraModule, AMissingModuleIsAClearUnsupportedNamingWhereItWasLookedFor) {
    EXPECT_EXIT(
        {
            ::setenv("SLICESTATION_DRIVER_DIR", "/nonexistent-driver-dir", 1);
            auto c = drivers::openLibcameraCamera({});
            const bool clear =
                !c && c.error().code == ErrorCode::Unsupported &&
                c.error().message.find("/nonexistent-driver-dir/libslst_libcamera.so") !=
                    std::string::npos &&
                !mapped("libcamera.so");
            std::exit(clear ? 0 : 1);
        },
        ::testing::ExitedWithCode(0), "");
}

TEST(LibcameraModule, LibcameraIsLoadedOnlyWhenACameraIsAskedFor) {
    ::setenv("LIBCAMERA_LOG_LEVELS", "*:ERROR", 0);
    // The tests of one binary run in one process, in order: nothing has loaded it before.
    EXPECT_FALSE(mapped("libcamera.so"));
    EXPECT_FALSE(mapped("libslst_libcamera.so"));
    auto ids = drivers::listLibcameraCameras();
    ASSERT_TRUE(ids) << ids.error().message;
    EXPECT_TRUE(mapped("libslst_libcamera.so"));
    EXPECT_TRUE(mapped("libcamera.so"));
    if (!ids->empty())
        GTEST_SKIP() << "a camera is attached (" << ids->front()
                     << "): the no-camera path cannot run";
    auto c = drivers::openLibcameraCamera({});
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, ErrorCode::NotFound);
    EXPECT_NE(c.error().message.find("no camera found"), std::string::npos) << c.error().message;
    // The module's own checks hold through the loader too.
    drivers::LibcameraCameraConfig bad;
    bad.bufferCount = 0;
    EXPECT_EQ(drivers::openLibcameraCamera(bad).error().code, ErrorCode::InvalidArgument);
}

} // namespace
} // namespace slicestation::test
