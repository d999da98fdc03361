#include "slicestation/daemon/alerts/notifier.hpp"

#include <algorithm>
#include <iostream>
#include <utility>

namespace slicestation::daemon {

void Notifier::addChannel(AlertChannel channel) {
    std::lock_guard lock(mutex_);
    channels_.push_back(std::move(channel));
}

void Notifier::addListener(EventListener listener) {
    std::lock_guard lock(mutex_);
    listeners_.push_back(std::move(listener));
}

void Notifier::publish(const StationEvent& event) {
    std::vector<EventListener> listeners;
    {
        std::lock_guard lock(mutex_);
        listeners = listeners_;
    }
    for (const auto& l : listeners)
        l(event);
}

core::Result<std::int64_t> Notifier::raise(AlertKind kind, AlertSeverity severity,
                                           const std::string& message,
                                           std::optional<std::int64_t> runId,
                                           std::optional<std::int64_t> sectionId) {
    AlertRecord a;
    a.kind = kind;
    a.severity = severity;
    a.message = message;
    a.runId = runId;
    a.sectionId = sectionId;
    a.raisedUtc = Journal::nowUtc();
    (void)storeHeldAlerts(); // older ones first, when there is space again
    auto id = journal_.raiseAlert(a);
    bool logged = true;
    if (id) {
        a.id = *id;
    } else {
        std::lock_guard lock(heldMutex_);
        const bool same = std::any_of(held_.begin(), held_.end(), [&](const AlertRecord& h) {
            return h.kind == a.kind && h.runId == a.runId && h.sectionId == a.sectionId &&
                   h.message == a.message;
        });
        if (same) {
            logged = false; // said already, and held
        } else {
            if (held_.size() >= kMaxHeldAlerts) {
                std::cerr << "<4>ALERT " << toString(held_.front().kind) << " raised at "
                          << held_.front().raisedUtc << " is dropped: " << kMaxHeldAlerts
                          << " alerts wait to be stored" << std::endl;
                held_.erase(held_.begin());
            }
            a.id = nextHeldId_--;
            held_.push_back(a);
        }
    }
    if (!logged)
        return id;
    // sd-daemon priority prefixes: the systemd journal files the line at that level.
    std::cerr << "<" << syslogPriority(severity) << ">ALERT " << toString(kind) << ": " << message;
    if (!id)
        std::cerr << " (not stored yet, held until the journal can store it: " << id.error().message
                  << ")";
    std::cerr << std::endl;
    std::vector<AlertChannel> channels;
    {
        std::lock_guard lock(mutex_);
        channels = channels_;
    }
    for (const auto& c : channels)
        c(a);
    publish({"alert_raised", toJson(a)});
    return id;
}

core::Result<void> Notifier::runStateChanged(std::int64_t runId, RunState state,
                                             const std::string& reason) {
    auto set = journal_.setRunState(runId, state, reason);
    auto run = journal_.run(runId);
    const std::string name = run ? run->name : std::to_string(runId);
    if (set)
        publish({"run_state", {{"run_id", runId}, {"state", toString(state)}, {"reason", reason}}});
    AlertKind kind{};
    AlertSeverity severity{};
    switch (state) {
    case RunState::Finished:
        kind = AlertKind::RunFinished;
        severity = AlertSeverity::Info;
        break;
    case RunState::Paused:
        kind = AlertKind::RunPaused;
        severity = AlertSeverity::Warning;
        break;
    case RunState::Failed:
        kind = AlertKind::RunFailed;
        severity = AlertSeverity::Critical;
        break;
    case RunState::Cancelled:
        kind = AlertKind::RunCancelled;
        severity = AlertSeverity::Info;
        break;
    default:
        return set;
    }
    std::string msg = "run " + std::to_string(runId) + " \"" + name + "\" " + toString(state);
    if (run)
        msg += " (" + std::to_string(run->doneCount) + "/" + std::to_string(run->sectionCount) +
               " sections done)";
    if (!reason.empty())
        msg += ": " + reason;
    // Not stored (disk full): said all the same, and the caller learns it from the error.
    if (!set)
        msg += " (the journal could not store the new state: " + set.error().message + ")";
    (void)raise(kind, severity, msg, runId); // an alert the journal refuses is held, not lost
    return set;
}

std::vector<AlertRecord> Notifier::heldAlerts() const {
    std::lock_guard lock(heldMutex_);
    return held_;
}

std::size_t Notifier::storeHeldAlerts() {
    std::vector<std::pair<std::int64_t, AlertRecord>> stored; // held id, stored alert
    std::size_t left = 0;
    {
        std::lock_guard lock(heldMutex_);
        while (!held_.empty()) {
            AlertRecord a = held_.front();
            const std::int64_t heldId = a.id;
            auto id = journal_.raiseAlert(a);
            if (!id)
                break;
            a.id = *id;
            held_.erase(held_.begin());
            stored.emplace_back(heldId, a);
        }
        left = held_.size();
    }
    for (const auto& [heldId, a] : stored) {
        nlohmann::json ev = toJson(a);
        ev["held_id"] = heldId;
        publish({"alert_stored", ev});
    }
    return left;
}

core::Result<AlertRecord> Notifier::acknowledge(std::int64_t alertId, const std::string& action) {
    auto a = journal_.acknowledgeAlert(alertId, action);
    if (a)
        publish({"alert_acknowledged", toJson(*a)});
    return a;
}

} // namespace slicestation::daemon
