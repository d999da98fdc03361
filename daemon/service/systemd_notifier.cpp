#include "slicestation/daemon/service/systemd_notifier.hpp"

#include <systemd/sd-daemon.h>

#include <cstdlib>
#include <ctime>

namespace slicestation::daemon {

SystemdNotifier SystemdNotifier::fromEnvironment() {
    SystemdNotifier n;
    const char* socket = std::getenv("NOTIFY_SOCKET");
    n.enabled_ = socket != nullptr && *socket != '\0';
    if (!n.enabled_) {
        return n;
    }
    // sd_watchdog_enabled(3): > 0 when WATCHDOG_USEC is set and WATCHDOG_PID (if set) is us.
    std::uint64_t usec = 0;
    if (sd_watchdog_enabled(0, &usec) > 0 && usec > 0) {
        n.watchdogInterval_ = std::chrono::microseconds(static_cast<std::int64_t>(usec));
    }
    return n;
}

void SystemdNotifier::send(const std::string& message) {
    if (!enabled_) {
        return;
    }
    // sd_notify returns > 0 when sent, 0 when NOTIFY_SOCKET is unset, < 0 (-errno) on failure.
    if (sd_notify(0, message.c_str()) <= 0) {
        sendFailures_.fetch_add(1);
    }
}

void SystemdNotifier::ready() {
    send("READY=1");
}

void SystemdNotifier::status(const std::string& text) {
    // One assignment per line in the protocol: a newline in the text would inject others.
    std::string line = text;
    for (char& c : line) {
        if (c == '\n' || c == '\r')
            c = ' ';
    }
    send("STATUS=" + line);
}

void SystemdNotifier::stopping() {
    send("STOPPING=1");
}

void SystemdNotifier::watchdogPing() {
    send("WATCHDOG=1");
}

void SystemdNotifier::reloading() {
    // systemd >= 253 wants the CLOCK_MONOTONIC time of the reload request with RELOADING=1
    // (Type=notify-reload); older versions ignore the extra field.
    timespec ts{};
    clock_gettime(CLOCK_MONOTONIC, &ts);
    const auto usec = static_cast<std::uint64_t>(ts.tv_sec) * 1'000'000u +
                      static_cast<std::uint64_t>(ts.tv_nsec) / 1000u;
    send("RELOADING=1\nMONOTONIC_USEC=" + std::to_string(usec));
}

void SystemdNotifier::errnoStatus(int err) {
    send("ERRNO=" + std::to_string(err));
}

// ---------------------------------------------------------------------------------------------

ProgressWatchdog::ProgressWatchdog(SystemdNotifier& notifier, std::chrono::milliseconds stallLimit,
                                   core::Clock& clock)
    : notifier_(notifier), stallLimit_(stallLimit), clock_(clock) {
    lastProgressNs_ = clock_.now().time_since_epoch().count();
    const auto interval = notifier_.watchdogInterval();
    if (!notifier_.enabled() || !interval) {
        return; // systemd wants no pings: no thread
    }
    // sd_watchdog_enabled(3): "the daemon should call sd_notify(0, "WATCHDOG=1") ... every
    // half of the time returned in usec".
    period_ = std::chrono::duration_cast<std::chrono::nanoseconds>(*interval) / 2;
    thread_ = std::thread([this] { run(); });
}

ProgressWatchdog::~ProgressWatchdog() {
    stop();
}

void ProgressWatchdog::progress() noexcept {
    lastProgressNs_ = clock_.now().time_since_epoch().count();
}

void ProgressWatchdog::setIdle(bool idle) noexcept {
    if (!idle) {
        progress(); // leaving idle starts a fresh stall window
    }
    idle_ = idle;
}

void ProgressWatchdog::stop() noexcept {
    stop_.raise();
    if (thread_.joinable() && thread_.get_id() != std::this_thread::get_id()) {
        thread_.join();
    }
}

void ProgressWatchdog::run() noexcept {
    while (!stop_.raised()) {
        const core::TimePoint now = clock_.now();
        const auto sinceProgress =
            now.time_since_epoch() - std::chrono::nanoseconds(lastProgressNs_.load());
        if (idle_.load() || sinceProgress <= stallLimit_) {
            notifier_.watchdogPing();
            pings_.fetch_add(1);
        }
        if (!clock_.sleepUntil(now + period_, stop_)) {
            break;
        }
    }
}

} // namespace slicestation::daemon
