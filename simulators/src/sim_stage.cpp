#include "slicestation/sim/sim_stage.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

namespace slicestation::sim {

using core::ErrorCode;
using core::makeError;

core::Result<std::unique_ptr<SimStage>> SimStage::create(SimStageConfig config) {
    auto bad = [](const hw::AxisRange& r) { return !(r.minUm < r.maxUm); };
    if (bad(config.limits.x) || bad(config.limits.y) || (config.limits.z && bad(*config.limits.z)))
        return makeError(ErrorCode::InvalidArgument, "sim stage: limits: min must be below max");
    if (!(config.speedUmPerS > 0) || !(config.accelUmPerS2 > 0) || !(config.positionWindowUm > 0))
        return makeError(ErrorCode::InvalidArgument,
                         "sim stage: speed, acceleration and position window must be positive");
    if (config.pollInterval.count() <= 0)
        config.pollInterval = std::chrono::milliseconds(1);
    if (!config.clock)
        config.clock = std::make_shared<core::SteadyClock>();
    return std::unique_ptr<SimStage>(new SimStage(std::move(config)));
}

SimStage::SimStage(SimStageConfig config)
    : config_(std::move(config)), axes_{SimAxis(config_.start.xUm), SimAxis(config_.start.yUm),
                                        SimAxis(config_.start.zUm)} {}

SimAxis& SimStage::axis(char name) {
    return axes_[name == 'x' ? 0 : name == 'y' ? 1 : 2];
}

hw::StagePosition SimStage::peekPosition() const {
    std::lock_guard lock(mutex_);
    const auto now = config_.clock->now();
    auto& a = axes_;
    return {a[0].state(now).feedbackSteps, a[1].state(now).feedbackSteps,
            config_.limits.z ? a[2].state(now).feedbackSteps : 0.0};
}

core::Result<hw::StagePosition> SimStage::position(std::chrono::milliseconds) {
    return peekPosition();
}

void SimStage::stop() noexcept {
    stop_.raise();
    std::lock_guard lock(mutex_);
    const auto now = config_.clock->now();
    for (auto& a : axes_)
        a.halt(now);
}

core::Result<hw::StagePosition> SimStage::moveTo(const hw::StagePosition& target,
                                                 std::chrono::milliseconds timeout) {
    stop_.clear();
    if (auto r = hw::checkWithinLimits(config_.limits, target); !r)
        return r.error();
    {
        std::lock_guard lock(mutex_);
        const auto now = config_.clock->now();
        const double t[3] = {target.xUm, target.yUm, target.zUm};
        const int n = config_.limits.z ? 3 : 2;
        for (int i = 0; i < n; ++i)
            if (!axes_[i].startMove(t[i], config_.speedUmPerS, config_.accelUmPerS2, now)) {
                std::ostringstream os;
                os << "sim stage: axis "
                   << "xyz"[i] << " is in alarm (code " << axes_[i].state(now).alarmCode
                   << "); reset the alarm first";
                return makeError(ErrorCode::Alarm, os.str());
            }
    }
    return waitSettled(target, false, timeout);
}

core::Result<hw::StagePosition> SimStage::home(std::chrono::milliseconds timeout) {
    stop_.clear();
    {
        std::lock_guard lock(mutex_);
        const auto now = config_.clock->now();
        const int n = config_.limits.z ? 3 : 2;
        for (int i = 0; i < n; ++i)
            if (!axes_[i].startHome(config_.speedUmPerS, config_.accelUmPerS2, now))
                return makeError(ErrorCode::Alarm, std::string("sim stage: axis ") + "xyz"[i] +
                                                       " is in alarm; reset the alarm first");
    }
    return waitSettled({0, 0, 0}, true, timeout);
}

core::Result<hw::StagePosition> SimStage::waitSettled(const hw::StagePosition& target, bool homing,
                                                      std::chrono::milliseconds timeout) {
    auto& clock = *config_.clock;
    const auto deadline = clock.now() + timeout;
    const double t[3] = {target.xUm, target.yUm, target.zUm};
    const int n = config_.limits.z ? 3 : 2;
    core::TimePoint settledSince{};
    bool settling = false;
    std::string lastReason = "not started";
    for (;;) {
        const auto now = clock.now();
        if (observer_)
            observer_(peekPosition(), now);
        bool settled = true;
        {
            std::lock_guard lock(mutex_);
            for (int i = 0; i < n; ++i) {
                const AxisState s = axes_[i].state(now);
                if (s.alarmCode != 0) {
                    std::ostringstream os;
                    os << "sim stage: axis "
                       << "xyz"[i] << " alarm code " << s.alarmCode;
                    return makeError(ErrorCode::Alarm, os.str());
                }
                const bool done = !s.moving && s.inPosition && (!homing || s.homeEnd);
                const double err = std::abs(s.feedbackSteps - t[i]);
                if (!done || err > config_.positionWindowUm) {
                    settled = false;
                    std::ostringstream os;
                    os << "axis "
                       << "xyz"[i] << (done ? " in position but feedback " : " at ")
                       << s.feedbackSteps << " um, target " << t[i] << " um";
                    lastReason = os.str();
                }
            }
        }
        if (settled) {
            if (!settling)
                settledSince = now;
            settling = true;
            if (now - settledSince >= config_.settle)
                return peekPosition();
        } else {
            settling = false;
        }
        if (now >= deadline) {
            stop();
            return makeError(ErrorCode::Timeout,
                             "sim stage: not settled before the deadline (" + lastReason + ")");
        }
        if (!clock.sleepUntil(std::min(now + config_.pollInterval, deadline), stop_))
            return makeError(ErrorCode::Cancelled, "sim stage: stopped");
    }
}

core::Result<hw::StageAlarm> SimStage::alarm(std::chrono::milliseconds) {
    std::lock_guard lock(mutex_);
    const auto now = config_.clock->now();
    for (int i = 0; i < 3; ++i)
        if (auto c = axes_[i].state(now).alarmCode; c != 0)
            return hw::StageAlarm{true, c, std::string(1, "xyz"[i])};
    return hw::StageAlarm{};
}

core::Result<void> SimStage::resetAlarm(std::chrono::milliseconds) {
    std::lock_guard lock(mutex_);
    const auto now = config_.clock->now();
    for (auto& a : axes_)
        a.resetAlarm(now);
    return {};
}

} // namespace slicestation::sim
