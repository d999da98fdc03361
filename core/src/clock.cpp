#include "slicestation/core/clock.hpp"

namespace slicestation::core {

void StopSignal::raise() noexcept {
    {
        std::lock_guard lock(mutex_);
        raised_ = true;
    }
    cv_.notify_all();
}

void StopSignal::clear() noexcept {
    std::lock_guard lock(mutex_);
    raised_ = false;
}

bool StopSignal::waitUntil(TimePoint deadline) const {
    std::unique_lock lock(mutex_);
    return !cv_.wait_until(lock, deadline, [this] { return raised_.load(); });
}

bool VirtualClock::sleepUntil(TimePoint t, const StopSignal& stop) {
    if (stop.raised())
        return false;
    std::int64_t target = t.time_since_epoch().count();
    std::int64_t cur = nowNs_.load();
    while (cur < target && !nowNs_.compare_exchange_weak(cur, target)) {
    }
    return !stop.raised();
}

} // namespace slicestation::core
