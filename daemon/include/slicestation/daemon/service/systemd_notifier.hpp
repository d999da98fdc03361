#pragma once
/// The daemon's side of the systemd service protocol (sd_notify(3)) and a progress-gated
/// watchdog.
///
/// SystemdNotifier sends READY/STATUS/STOPPING/RELOADING/WATCHDOG messages to $NOTIFY_SOCKET.
/// Outside systemd (no NOTIFY_SOCKET) it is disabled and every call is a no-op, so the daemon
/// runs the same in a terminal. Send failures are not errors for the caller (systemd notices a
/// missing READY or WATCHDOG by itself); they are counted in sendFailures().
/// Threading: every method may be called from any thread (sd_notify opens a socket per call;
/// the notifier's own state is fixed at construction).
///
/// ProgressWatchdog pings WATCHDOG=1 every half watchdog interval, but only while the scan loop
/// is making progress (progress() called within `stallLimit`) or is legitimately idle. A hung
/// move or capture stops the pings, so systemd kills (SIGABRT) and restarts the daemon.

#include "slicestation/core/clock.hpp"

#include <atomic>
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <thread>

namespace slicestation::daemon {

class SystemdNotifier {
public:
    /// A disabled notifier (every call is a no-op).
    SystemdNotifier() = default;

    /// Reads NOTIFY_SOCKET, WATCHDOG_USEC and WATCHDOG_PID (the environment is left as it is,
    /// so child processes would see it too: the daemon starts none). The watchdog interval is
    /// set only when WATCHDOG_USEC is a positive number and WATCHDOG_PID, if present, is ours.
    static SystemdNotifier fromEnvironment();

    /// False outside systemd: every call is then a no-op.
    bool enabled() const noexcept { return enabled_; }
    /// WatchdogSec= of the unit, when systemd asked for pings; ping at half of it.
    std::optional<std::chrono::microseconds> watchdogInterval() const noexcept {
        return watchdogInterval_;
    }

    void ready();                         ///< READY=1: devices and database are up
    void status(const std::string& text); ///< STATUS=<text> (newlines become spaces)
    void stopping();                      ///< STOPPING=1: shutting down
    void watchdogPing();                  ///< WATCHDOG=1
    void reloading();                     ///< RELOADING=1 with MONOTONIC_USEC (systemd >= 253)
    /// ERRNO=<n>: the errno-style reason of a fatal error, sent before exiting non-zero.
    void errnoStatus(int err);

    /// Messages that could not be sent (NOTIFY_SOCKET gone, ...), since construction.
    std::uint64_t sendFailures() const noexcept { return sendFailures_.load(); }

    SystemdNotifier(const SystemdNotifier& other)
        : enabled_(other.enabled_), watchdogInterval_(other.watchdogInterval_) {}
    SystemdNotifier& operator=(const SystemdNotifier& other) {
        enabled_ = other.enabled_;
        watchdogInterval_ = other.watchdogInterval_;
        return *this;
    }

private:
    void send(const std::string& message);

    bool enabled_ = false;
    std::optional<std::chrono::microseconds> watchdogInterval_;
    std::atomic<std::uint64_t> sendFailures_{0};
};

/// Owns one thread that pings the notifier's watchdog at half its interval while the scan loop
/// makes progress or is idle. When the notifier is disabled or systemd set no WatchdogSec=, no
/// thread is started and everything is a no-op.
///
/// The watchdog starts "just made progress" and not idle: the owner must call progress() or
/// setIdle(true) within `stallLimit` of construction. Time comes from `clock` (borrowed; must
/// outlive the watchdog and be thread-safe); the thread waits with clock.sleepUntil, so stop()
/// wakes it at once.
class ProgressWatchdog {
public:
    ProgressWatchdog(SystemdNotifier& notifier, std::chrono::milliseconds stallLimit,
                     core::Clock& clock);
    ~ProgressWatchdog(); ///< stop() and join
    ProgressWatchdog(const ProgressWatchdog&) = delete;
    ProgressWatchdog& operator=(const ProgressWatchdog&) = delete;

    /// The scan loop made progress (a move settled, a frame arrived, a file was written).
    /// Any thread; cheap (one clock read and an atomic store).
    void progress() noexcept;
    /// True while legitimately idle (no run, or paused waiting for an operator): keep pinging.
    void setIdle(bool idle) noexcept;
    /// Ends the thread; idempotent; no ping is sent after it returns.
    void stop() noexcept;

    /// Pings sent so far (for tests and status pages).
    std::uint64_t pingsSent() const noexcept { return pings_.load(); }
    /// Whether a thread runs (false when systemd wants no watchdog).
    bool active() const noexcept { return thread_.joinable(); }

private:
    void run() noexcept;

    SystemdNotifier& notifier_;
    std::chrono::milliseconds stallLimit_;
    core::Clock& clock_;
    std::chrono::nanoseconds period_{0};
    std::atomic<std::int64_t> lastProgressNs_{0};
    std::atomic<bool> idle_{false};
    std::atomic<std::uint64_t> pings_{0};
    core::StopSignal stop_;
    std::thread thread_;
};

} // namespace slicestation::daemon
