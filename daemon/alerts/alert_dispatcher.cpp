#include "slicestation/daemon/alerts/alert_channels.hpp"

#include "alert_util.hpp"

#include "slicestation/core/unique_fd.hpp"
#include "slicestation/daemon/config/config_document.hpp"

#include <httplib.h>
#include <systemd/sd-journal.h>

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <sys/uio.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <deque>
#include <initializer_list>
#include <map>
#include <optional>
#include <string_view>
#include <thread>

extern char** environ; // NOLINT(readability-redundant-declaration): POSIX declares it nowhere

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using Clock = std::chrono::steady_clock;

// Dispatcher -----------------------------------------------------------------------------------

struct AlertDispatcher::Lane {
    std::unique_ptr<AlertChannelSink> sink;
    std::deque<AlertRecord> queue;
    std::deque<Clock::time_point> starts; ///< first attempts inside the rate window
    std::uint64_t heldCount = 0;          ///< alerts over the rate limit, not yet summarised
    std::map<std::string, std::uint64_t> heldKinds;
    AlertSeverity heldSeverity = AlertSeverity::Info; ///< the highest held
    bool busy = false;                                ///< delivering or waiting to retry
    bool done = false;                                ///< the worker has returned
    AlertChannelStats stats;
    std::thread thread;
};

AlertDispatcher::AlertDispatcher(const AlertSettings& policy,
                                 std::vector<std::unique_ptr<AlertChannelSink>> sinks,
                                 GiveUp onGiveUp)
    : retries_(std::max(0, policy.retries)), backoffInitial_(policy.backoffInitial),
      backoffMax_(std::max(policy.backoffMax, policy.backoffInitial)),
      rateWindow_(policy.rateWindow),
      maxPerWindow_(static_cast<std::size_t>(std::max(0, policy.maxPerWindow))),
      queueCapacity_(std::max<std::size_t>(1, policy.queueCapacity)),
      minSeverity_(policy.minSeverity), onGiveUp_(std::move(onGiveUp)) {
    for (auto& sink : sinks) {
        auto lane = std::make_unique<Lane>();
        lane->stats.name = sink->name();
        lane->sink = std::move(sink);
        lanes_.push_back(std::move(lane));
    }
    // Started only once lanes_ is complete: workers read it.
    for (auto& lane : lanes_)
        lane->thread = std::thread([this, l = lane.get()] { run(*l); });
}

AlertDispatcher::~AlertDispatcher() {
    stop(std::chrono::milliseconds(0));
}

void AlertDispatcher::post(const AlertRecord& alert) {
    if (alert.severity < minSeverity_)
        return;
    std::lock_guard lock(mutex_);
    if (stopping_)
        return;
    for (auto& lane : lanes_) {
        if (lane->queue.size() >= queueCapacity_) {
            lane->queue.pop_front();
            ++lane->stats.dropped;
        }
        lane->queue.push_back(alert);
    }
    cv_.notify_all();
}

std::vector<std::string> AlertDispatcher::channelNames() const {
    std::lock_guard lock(mutex_);
    std::vector<std::string> names;
    for (const auto& lane : lanes_)
        names.push_back(lane->stats.name);
    return names;
}

std::vector<AlertChannelStats> AlertDispatcher::stats() const {
    std::lock_guard lock(mutex_);
    std::vector<AlertChannelStats> s;
    for (const auto& lane : lanes_)
        s.push_back(lane->stats);
    return s;
}

bool AlertDispatcher::idleLocked() const {
    return std::all_of(lanes_.begin(), lanes_.end(), [](const auto& l) {
        return l->done || (l->queue.empty() && !l->busy && l->heldCount == 0);
    });
}

bool AlertDispatcher::waitIdle(std::chrono::milliseconds timeout) const {
    std::unique_lock lock(mutex_);
    return cv_.wait_for(lock, timeout, [this] { return idleLocked(); });
}

void AlertDispatcher::stop(std::chrono::milliseconds drainTimeout) noexcept {
    std::lock_guard joinLock(joinMutex_);
    std::unique_lock lock(mutex_);
    if (!stopping_) {
        stopping_ = true;
        deadline_ = Clock::now() + drainTimeout;
    }
    cv_.notify_all();
    cv_.wait_until(lock, deadline_, [this] {
        return std::all_of(lanes_.begin(), lanes_.end(), [](const auto& l) { return l->done; });
    });
    // Past the deadline: cut short what is still being delivered (a hung command, a slow server).
    // Outside the lock: a webhook's cancel may wait for a connect in progress.
    std::vector<AlertChannelSink*> running;
    for (auto& lane : lanes_)
        if (!lane->done)
            running.push_back(lane->sink.get());
    lock.unlock();
    for (auto* sink : running)
        sink->cancel();
    for (auto& lane : lanes_)
        if (lane->thread.joinable())
            lane->thread.join();
}

void AlertDispatcher::run(Lane& lane) {
    std::unique_lock lock(mutex_);
    for (;;) {
        const auto now = Clock::now();
        if (stopping_ && now >= deadline_)
            break;
        while (!lane.starts.empty() && lane.starts.front() + rateWindow_ <= now)
            lane.starts.pop_front();
        const bool room = maxPerWindow_ == 0 || lane.starts.size() < maxPerWindow_;
        if (!room) {
            for (const auto& a : lane.queue) {
                ++lane.heldCount;
                ++lane.heldKinds[toString(a.kind)]; // by name: the summary lists them so
                lane.heldSeverity = std::max(lane.heldSeverity, a.severity);
                ++lane.stats.suppressed;
            }
            lane.queue.clear();
        }
        std::optional<AlertRecord> next;
        // Held alerts go out as one summary once the window has room, or at once when stopping.
        if (lane.heldCount > 0 && (room || stopping_)) {
            AlertRecord s;
            s.kind = AlertKind::AlertSummary;
            s.severity = lane.heldSeverity;
            s.raisedUtc = Journal::nowUtc();
            std::string kinds;
            for (const auto& [kind, n] : lane.heldKinds)
                kinds += (kinds.empty() ? "" : ", ") + kind +
                         (n > 1 ? " (x" + std::to_string(n) + ")" : "");
            s.message = std::to_string(lane.heldCount) + " more alerts: kinds " + kinds +
                        "; held by the rate limit of this channel, see slicectl alerts";
            lane.heldCount = 0;
            lane.heldKinds.clear();
            lane.heldSeverity = AlertSeverity::Info;
            ++lane.stats.summaries;
            next = std::move(s);
        } else if (room && !lane.queue.empty()) {
            next = std::move(lane.queue.front());
            lane.queue.pop_front();
        }
        if (!next) {
            if (stopping_)
                break;
            if (lane.heldCount > 0)
                cv_.wait_until(lock, lane.starts.front() + rateWindow_);
            else
                cv_.wait(lock);
            continue;
        }
        lane.starts.push_back(now);
        lane.busy = true;
        deliverWithRetries(lane, *next, lock);
        lane.busy = false;
        cv_.notify_all();
    }
    lane.stats.dropped += lane.queue.size() + lane.heldCount;
    lane.queue.clear();
    lane.heldCount = 0;
    lane.done = true;
    cv_.notify_all();
}

void AlertDispatcher::deliverWithRetries(Lane& lane, const AlertRecord& alert,
                                         std::unique_lock<std::mutex>& lock) {
    auto backoff = backoffInitial_;
    for (int attempt = 0;; ++attempt) {
        lock.unlock();
        auto r = lane.sink->deliver(alert);
        lock.lock();
        if (r) {
            ++lane.stats.delivered;
            return;
        }
        lane.stats.lastError = r.error().message;
        bool giveUp = attempt >= retries_ || !lane.sink->retryFailures() ||
                      r.error().code == ErrorCode::Cancelled ||
                      (stopping_ && Clock::now() >= deadline_);
        if (!giveUp) {
            // The wait ends early only at the stop deadline; stop() notifies so it is seen.
            const auto retryAt = Clock::now() + backoff;
            for (;;) {
                const auto until = stopping_ ? std::min(retryAt, deadline_) : retryAt;
                if (Clock::now() >= until)
                    break;
                cv_.wait_until(lock, until);
            }
            giveUp = stopping_ && Clock::now() >= deadline_;
        }
        if (giveUp) {
            ++lane.stats.failed;
            if (onGiveUp_) {
                const auto callback = onGiveUp_;
                const std::string channel = lane.stats.name;
                lock.unlock();
                callback(channel, alert, r.error());
                lock.lock();
            }
            return;
        }
        ++lane.stats.retried;
        backoff = std::min(backoff * 2, backoffMax_);
    }
}

} // namespace slicestation::daemon
