#pragma once
/// Time for devices and simulators, injectable so tests never sleep.
///
/// A Clock tells the time and waits until a time point unless a StopSignal is raised first.
/// SteadyClock waits for real; VirtualClock jumps to the time point at once, so simulated moves
/// that "take" seconds complete instantly and deterministically in tests.
/// Threading: StopSignal is fully thread-safe (raise() from any thread). SteadyClock is
/// thread-safe; VirtualClock is thread-safe (time only moves forward).

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>

namespace slicestation::core {

using TimePoint = std::chrono::steady_clock::time_point;

/// A latch that preempts waits: raise() wakes every wait in progress and makes later waits
/// return at once until clear().
class StopSignal {
public:
    void raise() noexcept;
    void clear() noexcept;
    bool raised() const noexcept { return raised_.load(); }
    /// Blocks until `deadline` (steady clock) or raise(); returns false when raised.
    bool waitUntil(TimePoint deadline) const;

private:
    mutable std::mutex mutex_;
    mutable std::condition_variable cv_;
    std::atomic<bool> raised_{false};
};

class Clock {
public:
    virtual ~Clock() = default;
    virtual TimePoint now() const = 0;
    /// Waits until `t`; returns false (early) when `stop` is raised.
    virtual bool sleepUntil(TimePoint t, const StopSignal& stop) = 0;
};

class SteadyClock final : public Clock {
public:
    TimePoint now() const override { return std::chrono::steady_clock::now(); }
    bool sleepUntil(TimePoint t, const StopSignal& stop) override { return stop.waitUntil(t); }
};

/// Simulated time: starts at a fixed epoch and advances only when someone waits or calls
/// advance(). Waits return immediately.
class VirtualClock final : public Clock {
public:
    TimePoint now() const override { return TimePoint(std::chrono::nanoseconds(nowNs_.load())); }
    bool sleepUntil(TimePoint t, const StopSignal& stop) override;
    void advance(std::chrono::nanoseconds d) { nowNs_ += d.count(); }

private:
    std::atomic<std::int64_t> nowNs_{1'000'000'000};
};

} // namespace slicestation::core
