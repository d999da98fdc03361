#include "slicestation/sim/sim_axis.hpp"

#include <algorithm>
#include <cmath>

namespace slicestation::sim {

namespace {
double seconds(core::TimePoint a, core::TimePoint b) {
    return std::chrono::duration<double>(b - a).count();
}
} // namespace

void SimAxis::start(double target, double speed, double accel, core::TimePoint now, bool homing) {
    update(now);
    const double here = frozen_ ? frozenAt_ : profilePosition(seconds(t0_, now));
    p0_ = here;
    p1_ = target;
    t0_ = now;
    accel_ = std::max(accel, 1e-9);
    speed = std::max(speed, 1e-9);
    const double d = std::abs(p1_ - p0_);
    rampS_ = speed / accel_;
    if (accel_ * rampS_ * rampS_ >= d) { // triangular profile
        rampS_ = std::sqrt(d / accel_);
        peakSpeed_ = accel_ * rampS_;
        durationS_ = 2 * rampS_;
    } else {
        peakSpeed_ = speed;
        durationS_ = 2 * rampS_ + (d - accel_ * rampS_ * rampS_) / speed;
    }
    active_ = true;
    frozen_ = false;
    homing_ = homing;
    homeEnd_ = false;
    inPosition_ = false;
    moveAlarm_ = armedAlarm_;
    armedAlarm_ = 0;
    faultThisMove_ = stall_ || moveAlarm_ != 0;
}

bool SimAxis::startMove(double targetSteps, double speed, double accel, core::TimePoint now) {
    update(now);
    if (alarm_ != 0)
        return false;
    start(targetSteps, speed, accel, now, false);
    return true;
}

bool SimAxis::startHome(double speed, double accel, core::TimePoint now) {
    update(now);
    if (alarm_ != 0)
        return false;
    start(0.0, speed, accel, now, true);
    return true;
}

double SimAxis::profilePosition(double t) const {
    if (!active_)
        return p1_;
    const double d = std::abs(p1_ - p0_);
    const double dir = p1_ >= p0_ ? 1.0 : -1.0;
    double s;
    if (t <= 0)
        s = 0;
    else if (t >= durationS_)
        s = d;
    else if (t < rampS_)
        s = 0.5 * accel_ * t * t;
    else if (t < durationS_ - rampS_)
        s = 0.5 * accel_ * rampS_ * rampS_ + peakSpeed_ * (t - rampS_);
    else
        s = d - 0.5 * accel_ * (durationS_ - t) * (durationS_ - t);
    return p0_ + dir * std::min(s, d);
}

void SimAxis::update(core::TimePoint now) {
    if (!active_ || frozen_)
        return;
    const double t = seconds(t0_, now);
    if (faultThisMove_ && t >= durationS_ / 2) {
        frozen_ = true;
        frozenAt_ = profilePosition(durationS_ / 2);
        if (moveAlarm_ != 0) { // an alarm stops the motor; a stall keeps "moving" forever
            alarm_ = moveAlarm_;
            moveAlarm_ = 0;
            active_ = false;
            homing_ = false;
            p1_ = frozenAt_;
        }
        return;
    }
    if (t >= durationS_) {
        active_ = false;
        inPosition_ = true;
        if (homing_) {
            homing_ = false;
            homeEnd_ = true;
        }
    }
}

void SimAxis::halt(core::TimePoint now) {
    update(now);
    const double here = frozen_ ? frozenAt_ : profilePosition(seconds(t0_, now));
    active_ = false;
    frozen_ = false;
    homing_ = false;
    p0_ = p1_ = here;
    inPosition_ = false; // stopped short of the target
}

void SimAxis::resetAlarm(core::TimePoint now) {
    update(now);
    alarm_ = 0;
}

void SimAxis::raiseAlarm(std::uint32_t code, core::TimePoint now) {
    halt(now);
    alarm_ = code;
}

AxisState SimAxis::state(core::TimePoint now) {
    update(now);
    AxisState s;
    s.commandSteps = frozen_ ? frozenAt_ : profilePosition(seconds(t0_, now));
    s.feedbackSteps = s.commandSteps + driftSteps_;
    s.targetSteps = p1_;
    s.moving = active_;
    s.inPosition = inPosition_ && !active_ && alarm_ == 0;
    s.homing = homing_ && active_;
    s.homeEnd = homeEnd_;
    s.alarmCode = alarm_;
    return s;
}

} // namespace slicestation::sim
