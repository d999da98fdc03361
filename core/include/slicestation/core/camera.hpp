#pragma once
/// Camera. Models: drivers::V4l2Camera, drivers::LibcameraCamera, sim::SimCamera,
/// sim::FaultyCamera.
///
/// Threading: one owning thread calls everything except stop(), which may be called from any
/// thread and preempts a capture in progress (it returns Cancelled).
/// Errors: InvalidArgument (a setting the model cannot take), Timeout (no frame before the
/// deadline), Disconnected (the device went away and could not be brought back),
/// IoError (a corrupt frame or a failing call), NotFound (no such device), Cancelled.

#include "slicestation/core/frame.hpp"
#include "slicestation/core/result.hpp"

#include <chrono>
#include <cstdint>

namespace slicestation::hw {

/// What a run asks for. Exposure, gain and white balance stay locked for the whole run so tiles
/// match; nothing automatic is left on.
struct CameraSettings {
    PixelFormat format = PixelFormat::Mono8;
    int width = 640;
    int height = 480;
    std::int64_t exposureUs = 10'000;
    double analogueGain = 1.0;
    double redGain = 1.0; ///< white balance (ignored by mono sensors)
    double blueGain = 1.0;
};

class Camera {
public:
    virtual ~Camera() = default;
    /// Applies `settings`, blocking up to `timeout`. Devices may adjust the size or exposure;
    /// \return the settings actually in force (read back from the device).
    [[nodiscard]] virtual core::Result<CameraSettings>
    configure(const CameraSettings& settings, std::chrono::milliseconds timeout) = 0;
    /// Captures one frame with the configured settings; blocks up to `timeout`.
    /// Models that need it configure themselves with default settings first.
    [[nodiscard]] virtual core::Result<Frame> capture(std::chrono::milliseconds timeout) = 0;
    /// Preempts a capture in progress; idempotent, safe in every state and from any thread.
    virtual void stop() noexcept = 0;
};

} // namespace slicestation::hw
