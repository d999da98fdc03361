#include "slicestation/sim/faulty_stage.hpp"

namespace slicestation::sim {

using core::ErrorCode;
using core::makeError;

core::Result<std::unique_ptr<FaultyStage>> FaultyStage::create(std::unique_ptr<hw::Stage> inner,
                                                               std::shared_ptr<core::Clock> clock) {
    if (!inner)
        return makeError(ErrorCode::InvalidArgument, "faulty stage: no stage to decorate");
    if (!clock)
        clock = std::make_shared<core::SteadyClock>();
    return std::unique_ptr<FaultyStage>(new FaultyStage(std::move(inner), std::move(clock)));
}

std::optional<core::Error> FaultyStage::scripted(Op op) {
    if (callsLeft_ == 0)
        return makeError(ErrorCode::Disconnected, "faulty stage: injected disconnect");
    if (callsLeft_ > 0)
        --callsLeft_;
    if (auto it = failNext_.find(op); it != failNext_.end()) {
        core::Error e = std::move(it->second);
        failNext_.erase(it);
        return e;
    }
    return std::nullopt;
}

core::Error FaultyStage::stall(std::chrono::milliseconds timeout) {
    if (!clock_->sleepUntil(clock_->now() + timeout, stop_))
        return makeError(ErrorCode::Cancelled, "faulty stage: stopped during a stalled move");
    inner_->stop();
    return makeError(ErrorCode::Timeout, "faulty stage: injected stall, never in position");
}

core::Result<hw::StagePosition> FaultyStage::position(std::chrono::milliseconds timeout) {
    if (auto e = scripted(Op::Position))
        return *e;
    return inner_->position(timeout);
}

core::Result<hw::StagePosition> FaultyStage::moveTo(const hw::StagePosition& target,
                                                    std::chrono::milliseconds timeout) {
    stop_.clear();
    if (auto e = scripted(Op::Move))
        return *e;
    if (auto r = hw::checkWithinLimits(inner_->limits(), target); !r)
        return r.error();
    if (latchedAlarm_ != 0)
        return makeError(ErrorCode::Alarm, "faulty stage: alarm " + std::to_string(latchedAlarm_) +
                                               " is active; reset it first");
    if (alarmOnMove_ != 0) {
        latchedAlarm_ = alarmOnMove_;
        alarmOnMove_ = 0;
        inner_->stop();
        return makeError(ErrorCode::Alarm,
                         "faulty stage: injected alarm " + std::to_string(latchedAlarm_));
    }
    if (stall_)
        return stall(timeout);
    return inner_->moveTo(target, timeout);
}

core::Result<hw::StagePosition> FaultyStage::home(std::chrono::milliseconds timeout) {
    stop_.clear();
    if (auto e = scripted(Op::Home))
        return *e;
    if (latchedAlarm_ != 0)
        return makeError(ErrorCode::Alarm, "faulty stage: alarm is active; reset it first");
    if (stall_)
        return stall(timeout);
    return inner_->home(timeout);
}

void FaultyStage::stop() noexcept {
    stop_.raise();
    inner_->stop();
}

core::Result<hw::StageAlarm> FaultyStage::alarm(std::chrono::milliseconds timeout) {
    if (auto e = scripted(Op::Alarm))
        return *e;
    if (latchedAlarm_ != 0)
        return hw::StageAlarm{true, latchedAlarm_, "x"};
    return inner_->alarm(timeout);
}

core::Result<void> FaultyStage::resetAlarm(std::chrono::milliseconds timeout) {
    if (auto e = scripted(Op::ResetAlarm))
        return *e;
    latchedAlarm_ = 0;
    return inner_->resetAlarm(timeout);
}

} // namespace slicestation::sim
