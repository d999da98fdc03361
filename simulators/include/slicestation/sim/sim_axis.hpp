#pragma once
/// The motion of one simulated drive axis, in steps, evaluated lazily at the time asked.
///
/// Moves follow a trapezoidal velocity profile (speed, acceleration), so they take time. Homing
/// runs to step 0 (the mechanical home) and sets homeEnd. Faults: a stalled axis stops half-way
/// and reports "moving" forever; an armed alarm halts the next move half-way and raises the
/// alarm code until resetAlarm(); drift offsets the feedback from the command position.
/// Shared by sim::SimStage (in process) and the stage-sim Modbus server.
/// Threading: not thread-safe; the owner serialises calls.

#include "slicestation/core/clock.hpp"

#include <cstdint>

namespace slicestation::sim {

struct AxisState {
    double commandSteps = 0;  ///< where the profile says the axis is
    double feedbackSteps = 0; ///< what the encoder reports (command + drift)
    double targetSteps = 0;
    bool moving = false;
    bool inPosition = true; ///< the last move or homing finished at its target
    bool homing = false;
    bool homeEnd = false; ///< homing has completed since power-up / last move
    std::uint32_t alarmCode = 0;
};

class SimAxis {
public:
    explicit SimAxis(double positionSteps = 0) : p0_(positionSteps), p1_(positionSteps) {}

    /// Starts an absolute move; ignored (returns false) while in alarm. speed > 0, accel > 0.
    bool startMove(double targetSteps, double speedStepsPerS, double accelStepsPerS2,
                   core::TimePoint now);
    /// Starts homing towards step 0; ignored (returns false) while in alarm.
    bool startHome(double speedStepsPerS, double accelStepsPerS2, core::TimePoint now);
    /// Stops at once where the axis is now (a simulation shortcut for a decelerated stop).
    void halt(core::TimePoint now);
    void resetAlarm(core::TimePoint now);
    AxisState state(core::TimePoint now);

    // Faults.
    void setStall(bool stall) { stall_ = stall; }
    /// The next move or homing stops half-way with this alarm code (0 disarms).
    void armAlarm(std::uint32_t code) { armedAlarm_ = code; }
    void setDriftSteps(double steps) { driftSteps_ = steps; }
    /// Raises an alarm at once (e.g. an alarm present at power-up).
    void raiseAlarm(std::uint32_t code, core::TimePoint now);

private:
    double profilePosition(double tS) const;
    void start(double target, double speed, double accel, core::TimePoint now, bool homing);
    void update(core::TimePoint now);

    double p0_ = 0, p1_ = 0; // start and target of the current profile
    core::TimePoint t0_{};   // profile start
    double durationS_ = 0, rampS_ = 0, peakSpeed_ = 0, accel_ = 1;
    bool active_ = false, homing_ = false, homeEnd_ = false, inPosition_ = true;
    double frozenAt_ = 0; // where a stalled/alarmed/halted axis stopped
    bool frozen_ = false;
    bool stall_ = false;
    bool faultThisMove_ = false; // stall or alarm applies to the current profile
    std::uint32_t armedAlarm_ = 0, moveAlarm_ = 0, alarm_ = 0;
    double driftSteps_ = 0;
};

} // namespace slicestation::sim
