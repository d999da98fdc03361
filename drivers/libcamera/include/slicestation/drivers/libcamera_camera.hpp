#pragma once
/// hw::Camera on libcamera (Debian 12's 0.0.3; Raspberry Pi CSI sensors, UVC through libcamera).
///
/// Flow (shared/reference/capture-apis.md §5.1): one CameraManager, acquire, StillCapture
/// configuration (the pixel format and size libcamera settles on after validate() are re-read
/// and reported), a FrameBufferAllocator, one request per buffer, manual controls (AeEnable
/// off, ExposureTime, AnalogueGain, AwbEnable off, ColourGains) on start and on every request.
/// Completed requests are handed from libcamera's thread to the owning thread through a mutex
/// and condition variable. Frames completed before capture() began are requeued unseen, and
/// `settleFrames` are dropped after (re)starting. A frame that does not come within
/// `frameTimeout` restarts the camera (stop/start, rpicam-apps PR #363), at most `maxRestarts`
/// times per capture. Camera removal (Camera::disconnected, CameraManager::cameraRemoved) makes
/// captures try to re-acquire the camera by id once per call, else Disconnected.
///
/// Ownership: libcamera allows ONE CameraManager per process, so at most one LibcameraCamera
/// may exist at a time (a second create() returns Unsupported).
/// Errors: create: NotFound (libcamera lists no camera, or none with that id), IoError
/// (CameraManager::start or acquire failed, e.g. camera busy), Unsupported (second instance).
/// configure: InvalidArgument (settings), Unsupported (no decodable format), IoError
/// (configure, allocation, mmap), Disconnected. capture: Timeout, Disconnected, IoError (a
/// frame with an error status), Cancelled (stop()).
/// Tested here only through the no-camera path (no camera on the build machine).
///
/// Loading: this class lives in its own shared library, libslst_libcamera.so, which the
/// station's programs load on first use through openLibcameraCamera / listLibcameraCameras
/// below (docs/hardware.md, "The libcamera driver is loaded when used"): libcamera and what it
/// brings (lttng-ust, gnutls, libdw, libudev) cost every process about 10 ms to load and
/// start, and only a station with a libcamera camera needs them.

#include "slicestation/core/camera.hpp"

#include <chrono>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::drivers {

struct LibcameraCameraConfig {
    std::string cameraId; ///< empty: the first camera libcamera lists
    int bufferCount = 3;
    int settleFrames = 2;
    std::chrono::milliseconds frameTimeout{2000}; ///< plus 5 x the exposure
    int maxRestarts = 2;
};

class LibcameraCamera final : public hw::Camera {
public:
    static core::Result<std::unique_ptr<LibcameraCamera>> create(LibcameraCameraConfig config);
    ~LibcameraCamera() override;
    LibcameraCamera(const LibcameraCamera&) = delete;
    LibcameraCamera& operator=(const LibcameraCamera&) = delete;

    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& settings,
                                               std::chrono::milliseconds timeout) override;
    core::Result<hw::Frame> capture(std::chrono::milliseconds timeout) override;
    void stop() noexcept override;

    /// The ids of the cameras libcamera lists now (starts a CameraManager: only when no
    /// LibcameraCamera exists). Empty when there is none.
    static core::Result<std::vector<std::string>> listCameras();

    struct Impl;

private:
    explicit LibcameraCamera(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
};

/// What libslst_libcamera.so exports, as `slst_libcamera_driver()`: the two entry points, and
/// the layout's version (the module must come from the same build as the program).
struct LibcameraDriver {
    static constexpr int kAbi = 1;
    int abi = kAbi;
    core::Result<std::unique_ptr<hw::Camera>> (*open)(const LibcameraCameraConfig&) = nullptr;
    core::Result<std::vector<std::string>> (*list)() = nullptr;
};

/// LibcameraCamera::create through the module, loaded on the first call of either function
/// (and kept: the cameras' code lives in it). The module is looked for in
/// $SLICESTATION_DRIVER_DIR only when that is set, else next to the running program, then in
/// the build tree's drivers/ folder.
/// \return Unsupported when the module cannot be loaded (the paths tried and the loader's
///         reason in the message), else what LibcameraCamera::create returns.
core::Result<std::unique_ptr<hw::Camera>> openLibcameraCamera(const LibcameraCameraConfig& config);
/// LibcameraCamera::listCameras through the module (see openLibcameraCamera).
core::Result<std::vector<std::string>> listLibcameraCameras();

} // namespace slicestation::drivers
