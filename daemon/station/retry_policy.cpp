#include "slicestation/daemon/station/retry_policy.hpp"

namespace slicestation::daemon {

using core::ErrorCode;

bool worthRetrying(const core::Error& error) noexcept {
    return error.code != ErrorCode::Cancelled && error.code != ErrorCode::OutOfRange &&
           error.code != ErrorCode::Alarm;
}

core::Result<hw::StagePosition> moveWithRetries(hw::Stage& stage, const hw::StagePosition& target,
                                                std::chrono::milliseconds timeout, int retries) {
    core::Result<hw::StagePosition> r = stage.moveTo(target, timeout);
    for (int attempt = 0; !r && attempt < retries && worthRetrying(r.error()); ++attempt)
        r = stage.moveTo(target, timeout);
    return r;
}

core::Result<hw::CameraSettings> configureWithRetries(hw::Camera& camera,
                                                      const hw::CameraSettings& settings,
                                                      std::chrono::milliseconds timeout,
                                                      int retries) {
    core::Result<hw::CameraSettings> r = camera.configure(settings, timeout);
    for (int attempt = 0; !r && attempt < retries && worthRetrying(r.error()); ++attempt)
        r = camera.configure(settings, timeout);
    return r;
}

core::Result<hw::Frame> captureWithRetries(hw::Camera& camera, std::chrono::milliseconds timeout,
                                           int retries,
                                           const std::optional<hw::CameraSettings>& reinitialise) {
    core::Result<hw::Frame> r = camera.capture(timeout);
    for (int attempt = 0; !r && attempt < retries && worthRetrying(r.error()); ++attempt) {
        if (reinitialise) {
            camera.stop();
            if (auto c = camera.configure(*reinitialise, timeout); !c) {
                r = c.error();
                continue;
            }
        }
        r = camera.capture(timeout);
    }
    return r;
}

} // namespace slicestation::daemon
