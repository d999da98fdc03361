#pragma once
/// Decorates any hw::Camera with scripted faults: the next N captures time out (after waiting
/// their deadline on the injected clock, preempted by stop()), corrupt frames (IoError), or the
/// camera disconnects after N more frames (every later call: Disconnected).

#include "slicestation/core/camera.hpp"
#include "slicestation/core/clock.hpp"

#include <memory>

namespace slicestation::sim {

class FaultyCamera final : public hw::Camera {
public:
    static core::Result<std::unique_ptr<FaultyCamera>> create(std::unique_ptr<hw::Camera> inner,
                                                              std::shared_ptr<core::Clock> clock);
    void timeoutNext(int captures) { timeouts_ = captures; }
    void corruptNext(int captures) { corrupt_ = captures; }
    void disconnectAfter(int frames) { framesLeft_ = frames; }

    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& s,
                                               std::chrono::milliseconds t) override;
    core::Result<hw::Frame> capture(std::chrono::milliseconds timeout) override;
    void stop() noexcept override;

private:
    FaultyCamera(std::unique_ptr<hw::Camera> inner, std::shared_ptr<core::Clock> clock)
        : inner_(std::move(inner)), clock_(std::move(clock)) {}
    std::unique_ptr<hw::Camera> inner_;
    std::shared_ptr<core::Clock> clock_;
    core::StopSignal stop_;
    int timeouts_ = 0, corrupt_ = 0, framesLeft_ = -1;
};

} // namespace slicestation::sim
