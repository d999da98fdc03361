// Loads libslst_libcamera.so on first use (libcamera_camera.hpp, "Loading").
#include "slicestation/drivers/libcamera_camera.hpp"

#include <dlfcn.h>

#include <cstdlib>
#include <filesystem>
#include <mutex>
#include <string>
#include <vector>

namespace slicestation::drivers {
namespace {

using core::ErrorCode;
using core::makeError;

constexpr const char* kModule = "libslst_libcamera.so";

/// Where the module is looked for, in order: the folder the environment names, only; else next
/// to the running program, then the build tree's folder.
std::vector<std::filesystem::path> moduleDirs() {
    std::vector<std::filesystem::path> dirs;
    if (const char* env = std::getenv("SLICESTATION_DRIVER_DIR"); env && *env) {
        dirs.emplace_back(env);
        return dirs;
    }
    std::error_code ec;
    const auto self = std::filesystem::read_symlink("/proc/self/exe", ec);
    if (!ec)
        dirs.push_back(self.parent_path());
#ifdef SLST_BUILD_DRIVER_DIR
    dirs.emplace_back(SLST_BUILD_DRIVER_DIR);
#endif
    return dirs;
}

/// The module's entry points, loaded once per process (never unloaded: the cameras it made
/// run its code).
core::Result<const LibcameraDriver*> driver() {
    static std::mutex mutex;
    static const LibcameraDriver* loaded = nullptr;
    const std::lock_guard lock(mutex);
    if (loaded)
        return loaded;
    std::string tried;
    for (const auto& dir : moduleDirs()) {
        const std::string path = (dir / kModule).string();
        tried += "\n  " + path + ": ";
        if (!std::filesystem::exists(path)) {
            tried += "no such file";
            continue;
        }
        void* handle = ::dlopen(path.c_str(), RTLD_NOW | RTLD_LOCAL);
        if (!handle) {
            const char* why = ::dlerror();
            tried += why ? why : "dlopen failed";
            continue;
        }
        using Entry = const LibcameraDriver* (*)();
        const auto entry = reinterpret_cast<Entry>(::dlsym(handle, "slst_libcamera_driver"));
        const LibcameraDriver* d = entry ? entry() : nullptr;
        if (!d || d->abi != LibcameraDriver::kAbi || !d->open || !d->list) {
            tried += "not this build's libcamera driver";
            ::dlclose(handle);
            continue;
        }
        loaded = d;
        return loaded;
    }
    return makeError(ErrorCode::Unsupported,
                     std::string("libcamera: the driver module ") + kModule +
                         " could not be loaded (install it next to the program, or name its "
                         "folder in SLICESTATION_DRIVER_DIR); tried:" +
                         tried);
}

} // namespace

core::Result<std::unique_ptr<hw::Camera>> openLibcameraCamera(const LibcameraCameraConfig& config) {
    auto d = driver();
    if (!d)
        return d.error();
    return (*d)->open(config);
}

core::Result<std::vector<std::string>> listLibcameraCameras() {
    auto d = driver();
    if (!d)
        return d.error();
    return (*d)->list();
}

} // namespace slicestation::drivers
