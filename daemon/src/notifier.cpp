#include "slicestation/daemon/notifier.hpp"

#include <iostream>

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
    for (const auto& l : listeners) l(event);
}

core::Result<std::int64_t> Notifier::raise(const std::string& kind, const std::string& severity,
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
    auto id = journal_.raiseAlert(a);
    if (id) a.id = *id;
    // sd-daemon priority prefixes: the systemd journal files the line at that level.
    const char* prefix = severity == "critical" ? "<2>" : severity == "warning" ? "<4>" : "<5>";
    std::cerr << prefix << "ALERT " << kind << ": " << message;
    if (!id) std::cerr << " (could not be stored: " << id.error().message << ")";
    std::cerr << std::endl;
    std::vector<AlertChannel> channels;
    {
        std::lock_guard lock(mutex_);
        channels = channels_;
    }
    for (const auto& c : channels) c(a);
    publish({"alert_raised", toJson(a)});
    return id;
}

core::Result<void> Notifier::runStateChanged(std::int64_t runId, RunState state, const std::string& reason) {
    auto set = journal_.setRunState(runId, state, reason);
    if (!set) return set;
    auto run = journal_.run(runId);
    const std::string name = run ? run->name : std::to_string(runId);
    publish({"run_state", {{"run_id", runId}, {"state", toString(state)}, {"reason", reason}}});
    std::string kind, severity;
    switch (state) {
    case RunState::Finished: kind = "run_finished"; severity = "info"; break;
    case RunState::Paused: kind = "run_paused"; severity = "warning"; break;
    case RunState::Failed: kind = "run_failed"; severity = "critical"; break;
    case RunState::Cancelled: kind = "run_cancelled"; severity = "info"; break;
    default: return {};
    }
    std::string msg = "run " + std::to_string(runId) + " \"" + name + "\" " + toString(state);
    if (run) msg += " (" + std::to_string(run->doneCount) + "/" + std::to_string(run->sectionCount) + " sections done)";
    if (!reason.empty()) msg += ": " + reason;
    auto a = raise(kind, severity, msg, runId);
    if (!a) return a.error();
    return {};
}

core::Result<AlertRecord> Notifier::acknowledge(std::int64_t alertId, const std::string& action) {
    auto a = journal_.acknowledgeAlert(alertId, action);
    if (a) publish({"alert_acknowledged", toJson(*a)});
    return a;
}

} // namespace slicestation::daemon
