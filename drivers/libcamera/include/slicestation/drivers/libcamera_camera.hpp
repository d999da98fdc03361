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

} // namespace slicestation::drivers
