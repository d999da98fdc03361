#include "slicestation/sim/faulty_camera.hpp"

namespace slicestation::sim {

using core::ErrorCode;
using core::makeError;

core::Result<std::unique_ptr<FaultyCamera>>
FaultyCamera::create(std::unique_ptr<hw::Camera> inner, std::shared_ptr<core::Clock> clock) {
    if (!inner)
        return makeError(ErrorCode::InvalidArgument, "faulty camera: no camera to decorate");
    if (!clock)
        clock = std::make_shared<core::SteadyClock>();
    return std::unique_ptr<FaultyCamera>(new FaultyCamera(std::move(inner), std::move(clock)));
}

core::Result<hw::CameraSettings> FaultyCamera::configure(const hw::CameraSettings& s,
                                                         std::chrono::milliseconds t) {
    if (framesLeft_ == 0)
        return makeError(ErrorCode::Disconnected, "faulty camera: injected disconnect");
    return inner_->configure(s, t);
}

core::Result<hw::Frame> FaultyCamera::capture(std::chrono::milliseconds timeout) {
    stop_.clear();
    if (framesLeft_ == 0)
        return makeError(ErrorCode::Disconnected, "faulty camera: injected disconnect");
    if (timeouts_ > 0) {
        --timeouts_;
        if (!clock_->sleepUntil(clock_->now() + timeout, stop_))
            return makeError(ErrorCode::Cancelled, "faulty camera: stopped");
        return makeError(ErrorCode::Timeout, "faulty camera: injected frame timeout");
    }
    if (corrupt_ > 0) {
        --corrupt_;
        return makeError(ErrorCode::IoError, "faulty camera: injected corrupt frame");
    }
    auto f = inner_->capture(timeout);
    if (f && framesLeft_ > 0)
        --framesLeft_;
    return f;
}

void FaultyCamera::stop() noexcept {
    stop_.raise();
    inner_->stop();
}

} // namespace slicestation::sim
