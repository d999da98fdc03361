#pragma once
/// An in-process simulated XY(Z) stage: three SimAxis models in micrometres, moves that take
/// time on an injected Clock (VirtualClock in tests: instant and deterministic).
/// Threading as hw::Stage: one owning thread; stop() from any thread.

#include "slicestation/core/clock.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/sim/sim_axis.hpp"

#include <chrono>
#include <memory>
#include <mutex>

namespace slicestation::sim {

struct SimStageConfig {
    hw::StageLimits limits{{0, 75'000}, {0, 25'000}, hw::AxisRange{0, 5'000}};
    hw::StagePosition start{};
    double speedUmPerS = 20'000;
    double accelUmPerS2 = 100'000;
    double positionWindowUm = 1.0;
    std::chrono::milliseconds settle{20};
    std::chrono::milliseconds pollInterval{5};
    std::shared_ptr<core::Clock> clock; ///< null: a SteadyClock
};

class SimStage final : public hw::Stage {
public:
    /// InvalidArgument when limits are empty or inverted, or speed/accel/window not positive.
    static core::Result<std::unique_ptr<SimStage>> create(SimStageConfig config);

    hw::StageLimits limits() const override { return config_.limits; }
    core::Result<hw::StagePosition> position(std::chrono::milliseconds timeout) override;
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& target,
                                           std::chrono::milliseconds timeout) override;
    core::Result<hw::StagePosition> home(std::chrono::milliseconds timeout) override;
    void stop() noexcept override;
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds timeout) override;
    core::Result<void> resetAlarm(std::chrono::milliseconds timeout) override;
    /// Reports the feedback at every poll of a move's wait (pollInterval, stage clock).
    void setMoveObserver(hw::MoveObserver observer) override { observer_ = std::move(observer); }

    /// The axis models, for fault injection ('x', 'y', 'z'). Call from the owning thread.
    SimAxis& axis(char name);
    /// The current feedback position without a deadline; safe from any thread (used by
    /// SimCamera to render what lies under the objective).
    hw::StagePosition peekPosition() const;

private:
    explicit SimStage(SimStageConfig config);
    core::Result<hw::StagePosition> waitSettled(const hw::StagePosition& target, bool homing,
                                                std::chrono::milliseconds timeout);

    SimStageConfig config_;
    mutable std::mutex mutex_; // guards the axes: stop() and peekPosition() come from elsewhere
    mutable SimAxis axes_[3];
    core::StopSignal stop_;
    hw::MoveObserver observer_;
};

} // namespace slicestation::sim
