#pragma once
/// hw::Camera on a Video4Linux2 capture device (UVC webcams, USB microscope cameras, CSI
/// bridges that expose a single-planar /dev/videoN).
///
/// Flow (docs/hardware.md, shared/reference/capture-apis.md §5.2): non-blocking open, QUERYCAP
/// (VIDEO_CAPTURE and STREAMING required), S_FMT accepting what the driver adjusts (GREY, Y16,
/// YUYV, RGB24 or MJPEG; MJPEG is decoded), manual exposure and gain (auto exposure and auto
/// white balance off), MMAP buffers, STREAMON. The stream stays on between captures; each capture
/// first drains frames that were already waiting (taken before the call) and drops
/// `staleFrames` more, so the frame returned was exposed after capture() began. After configure
/// and after a re-initialisation, `settleFrames` more frames are dropped while exposure settles.
///
/// Unplug: POLLERR/POLLHUP or ENODEV from an ioctl tears everything down and re-opens the device
/// (open, QUERYCAP, S_FMT, controls, REQBUFS, mmap, STREAMON) up to `maxReinitAttempts` times per
/// capture, `reinitDelay` apart, within the capture's deadline; then Disconnected.
///
/// Units: exposure in µs; V4L2's exposure_time_absolute is in 100 µs steps, so the exposure in
/// force is rounded to 100 µs (read back and reported). Gain and white balance controls have
/// device-specific units: the control value is gain × `gainUnitsPerX` (wb: `wbUnitsPerX`).
///
/// Errors: create: NotFound (no such device node), Unsupported (not a single-planar streaming
/// capture device), IoError (open or QUERYCAP failed, e.g. EACCES, EBUSY).
/// configure: InvalidArgument (size, exposure or gain out of range, also when the device says
/// ERANGE), Unsupported (no format we can convert, no manual exposure control, gain/WB asked but
/// no such control), IoError (an ioctl or mmap failed, no buffers granted), Disconnected.
/// capture: Timeout, Disconnected (gone and not back after the attempts), IoError (a corrupt
/// buffer: error flag, bytesused too small, bad index, undecodable MJPEG; the buffer is requeued
/// and the next capture works), Cancelled (stop()).
/// Threading: one owning thread; stop() from any thread (preempts a capture within `pollSlice`).

#include "slicestation/core/camera.hpp"
#include "slicestation/core/clock.hpp"
#include "slicestation/drivers/v4l2_syscalls.hpp"

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::drivers {

struct V4l2CameraConfig {
    std::string device = "/dev/video0";
    std::shared_ptr<V4l2Syscalls> syscalls; ///< null: libc
    std::shared_ptr<core::Clock> clock;     ///< null: SteadyClock
    int bufferCount = 4;                    ///< asked of REQBUFS (the driver may grant fewer)
    int settleFrames = 3;                   ///< dropped after (re)configuring
    int staleFrames = 1;                    ///< dropped at each capture after the drain
    int maxReinitAttempts = 3;
    std::chrono::milliseconds reinitDelay{500};
    std::chrono::milliseconds pollSlice{100}; ///< longest single poll (bounds stop() latency)
    double gainUnitsPerX = 100;               ///< V4L2_CID_GAIN value for analogue gain 1.0 is 100
    double wbUnitsPerX = 1000;                ///< V4L2_CID_RED/BLUE_BALANCE per unit gain
};

class V4l2Camera final : public hw::Camera {
public:
    /// Opens the device and checks its capabilities; nothing streams yet.
    static core::Result<std::unique_ptr<V4l2Camera>> create(V4l2CameraConfig config);
    ~V4l2Camera() override;
    V4l2Camera(const V4l2Camera&) = delete;
    V4l2Camera& operator=(const V4l2Camera&) = delete;

    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& settings,
                                               std::chrono::milliseconds timeout) override;
    core::Result<hw::Frame> capture(std::chrono::milliseconds timeout) override;
    void stop() noexcept override { stop_.raise(); }

    /// How many times the device was re-opened after an unplug (since create).
    int reinitCount() const noexcept { return reinitCount_; }
    /// The V4L2 pixel format negotiated ("GREY", "Y16 ", "YUYV", "RGB3", "MJPG"), empty if none.
    std::string negotiatedFourcc() const;

    struct Device; // the open device: fd, buffers (v4l2_camera.cpp)

private:
    explicit V4l2Camera(V4l2CameraConfig config);
    core::Result<void> openDevice();
    core::Result<hw::CameraSettings> setUp(const hw::CameraSettings& wanted);
    void stopStreaming() noexcept;
    core::Result<void> reinitialise(core::TimePoint deadline, const std::string& why);
    core::Result<hw::Frame> waitFrame(core::TimePoint deadline);

    V4l2CameraConfig config_;
    std::unique_ptr<Device> dev_;
    hw::CameraSettings wanted_;  ///< what the caller asked (re-applied after an unplug)
    hw::CameraSettings inForce_; ///< what the device reported
    bool configured_ = false;
    int dropRemaining_ = 0;
    std::uint64_t sequenceBase_ = 0, lastSequence_ = 0;
    int reinitCount_ = 0;
    core::StopSignal stop_;
};

} // namespace slicestation::drivers
