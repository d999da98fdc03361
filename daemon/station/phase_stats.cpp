#include "slicestation/daemon/station/phase_stats.hpp"

#include <algorithm>
#include <numeric>

namespace slicestation::daemon {

void PhaseStats::add(const std::string& phase, std::chrono::steady_clock::duration d) {
    std::lock_guard lock(mutex_);
    ms_[phase].push_back(std::chrono::duration<double, std::milli>(d).count());
}

nlohmann::json PhaseStats::summary() const {
    std::lock_guard lock(mutex_);
    nlohmann::json out = nlohmann::json::object();
    for (const auto& [phase, values] : ms_) {
        if (values.empty())
            continue;
        std::vector<double> v = values;
        std::sort(v.begin(), v.end());
        const double total = std::accumulate(v.begin(), v.end(), 0.0);
        out[phase] = {{"count", v.size()},
                      {"total_s", total / 1000.0},
                      {"mean_ms", total / static_cast<double>(v.size())},
                      {"median_ms", v[v.size() / 2]},
                      {"max_ms", v.back()}};
    }
    return out;
}

} // namespace slicestation::daemon
