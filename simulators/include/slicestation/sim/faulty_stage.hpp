#pragma once
/// Decorates any hw::Stage with scripted faults, for tests of everything above a stage.
///
/// Faults: the next call of an operation fails with a given error; moves stall (never settle,
/// so they time out); the next move raises an alarm that stays until resetAlarm(); after N more
/// calls every call reports Disconnected. Waits use the injected clock and honour stop().
/// Threading as hw::Stage; fault setters are for the owning thread.

#include "slicestation/core/clock.hpp"
#include "slicestation/core/stage.hpp"

#include <map>
#include <memory>
#include <optional>

namespace slicestation::sim {

class FaultyStage final : public hw::Stage {
public:
    enum class Op { Position, Move, Home, Alarm, ResetAlarm };

    /// InvalidArgument when `inner` is null. A null clock means a SteadyClock.
    static core::Result<std::unique_ptr<FaultyStage>> create(std::unique_ptr<hw::Stage> inner,
                                                             std::shared_ptr<core::Clock> clock);

    void failNext(Op op, core::Error error) { failNext_[op] = std::move(error); }
    void stallMoves(bool stall) { stall_ = stall; }
    void alarmOnNextMove(std::uint32_t code) { alarmOnMove_ = code; }
    /// After `calls` more calls, every call returns Disconnected. Negative disables.
    void disconnectAfter(int calls) { callsLeft_ = calls; }

    hw::StageLimits limits() const override { return inner_->limits(); }
    core::Result<hw::StagePosition> position(std::chrono::milliseconds timeout) override;
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& target,
                                           std::chrono::milliseconds timeout) override;
    core::Result<hw::StagePosition> home(std::chrono::milliseconds timeout) override;
    void stop() noexcept override;
    void setMoveObserver(hw::MoveObserver observer) override {
        inner_->setMoveObserver(std::move(observer));
    }
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds timeout) override;
    core::Result<void> resetAlarm(std::chrono::milliseconds timeout) override;

private:
    FaultyStage(std::unique_ptr<hw::Stage> inner, std::shared_ptr<core::Clock> clock)
        : inner_(std::move(inner)), clock_(std::move(clock)) {}
    std::optional<core::Error> scripted(Op op);
    core::Error stall(std::chrono::milliseconds timeout);

    std::unique_ptr<hw::Stage> inner_;
    std::shared_ptr<core::Clock> clock_;
    core::StopSignal stop_;
    std::map<Op, core::Error> failNext_;
    bool stall_ = false;
    std::uint32_t alarmOnMove_ = 0;
    std::uint32_t latchedAlarm_ = 0;
    int callsLeft_ = -1;
};

} // namespace slicestation::sim
