#pragma once
/// Durations of the scan phases (move, focus, capture, write, register...), for the status API
/// and the overnight benchmark. Thread-safe.
#include <nlohmann/json.hpp>

#include <chrono>
#include <map>
#include <mutex>
#include <string>
#include <vector>

namespace slicestation::daemon {

class PhaseStats {
public:
    void add(const std::string& phase, std::chrono::steady_clock::duration d);
    /// {"phase": {"count", "total_s", "mean_ms", "median_ms", "max_ms"}...}
    nlohmann::json summary() const;

private:
    mutable std::mutex mutex_;
    std::map<std::string, std::vector<double>> ms_;
};

/// Adds the time from construction to destruction to `phase`.
class PhaseTimer {
public:
    PhaseTimer(PhaseStats& stats, std::string phase)
        : stats_(stats), phase_(std::move(phase)), t0_(std::chrono::steady_clock::now()) {}
    ~PhaseTimer() { stats_.add(phase_, std::chrono::steady_clock::now() - t0_); }
    PhaseTimer(const PhaseTimer&) = delete;
    PhaseTimer& operator=(const PhaseTimer&) = delete;

private:
    PhaseStats& stats_;
    std::string phase_;
    std::chrono::steady_clock::time_point t0_;
};

} // namespace slicestation::daemon
