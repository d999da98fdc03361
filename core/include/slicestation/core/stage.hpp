#pragma once
/// Motorised XY(Z) stage. Models: drivers::ModbusStage, sim::SimStage, sim::FaultyStage.
///
/// Units: micrometres in the stage frame. Threading: one owning thread calls everything except
/// stop(), which may be called from any thread and preempts the call in progress.
/// Errors common to all calls: Timeout (a deadline passed; for moves the drive was told to stop),
/// Disconnected (the device is gone), IoError (a protocol or I/O failure after retries),
/// Alarm (the drive reports an alarm; see alarm()), Cancelled (stop() preempted the call).

#include "slicestation/core/result.hpp"

#include <chrono>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>

namespace slicestation::hw {

struct StagePosition {
    double xUm = 0;
    double yUm = 0;
    double zUm = 0; ///< ignored when the stage has no Z axis
};

struct AxisRange {
    double minUm = 0;
    double maxUm = 0;
    bool contains(double um) const { return um >= minUm && um <= maxUm; }
};

struct StageLimits {
    AxisRange x;
    AxisRange y;
    std::optional<AxisRange> z; ///< empty for an XY stage
};

struct StageAlarm {
    bool active = false;
    std::uint32_t code = 0; ///< the drive's own alarm code (0 = none)
    std::string axis;       ///< "x", "y" or "z": the first axis found in alarm
};

/// OutOfRange naming the axis when `target` lies outside `limits`; the check every model makes
/// before sending or moving anything.
core::Result<void> checkWithinLimits(const StageLimits& limits, const StagePosition& target);

/// Receives feedback positions read while a move or homing is under way, with the stage clock's
/// time of the read. Called on the thread that called moveTo/home; must not block.
using MoveObserver =
    std::function<void(const StagePosition&, std::chrono::steady_clock::time_point)>;

class Stage {
public:
    virtual ~Stage() = default;
    /// Models that read feedback while they wait for a move report each read to `observer`
    /// (SimStage at every poll, ModbusStage at most every 200 ms); the others ignore it. Call
    /// from the owning thread, before moves.
    virtual void setMoveObserver(MoveObserver observer) { (void)observer; }
    /// Soft limits, fixed after create().
    virtual StageLimits limits() const = 0;
    /// Feedback position. Blocks for at most `timeout`.
    [[nodiscard]] virtual core::Result<StagePosition>
    position(std::chrono::milliseconds timeout) = 0;
    /// Moves every axis and blocks until settled: the drive says in position and not moving,
    /// AND the feedback is within the position window of the target, AND that held for the
    /// settle time. Soft limits are checked first: OutOfRange means nothing was sent or moved.
    /// \return the settled feedback position; OutOfRange, Timeout, Alarm, Cancelled, ...
    [[nodiscard]] virtual core::Result<StagePosition> moveTo(const StagePosition& target,
                                                             std::chrono::milliseconds timeout) = 0;
    /// Runs the drives' homing and blocks until done. \return the position after homing.
    [[nodiscard]] virtual core::Result<StagePosition> home(std::chrono::milliseconds timeout) = 0;
    /// Halts every axis now and preempts any wait in progress (which returns Cancelled).
    /// Idempotent, safe in every state and from any thread.
    virtual void stop() noexcept = 0;
    /// Reads the alarm state of every axis (never resets it).
    [[nodiscard]] virtual core::Result<StageAlarm> alarm(std::chrono::milliseconds timeout) = 0;
    /// Resets the alarms of every axis; only called when someone asks.
    [[nodiscard]] virtual core::Result<void> resetAlarm(std::chrono::milliseconds timeout) = 0;
};

} // namespace slicestation::hw
