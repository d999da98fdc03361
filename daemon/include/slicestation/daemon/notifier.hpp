#pragma once
/// The one place alerts and run-state events go through. Every alert is stored in the journal
/// first (it stays open until acknowledged), then logged once on stderr (the systemd journal
/// captures it) and handed to every registered channel. Every terminal state of a run
/// (finished, paused, failed, cancelled) is reported through runStateChanged(), so no abort path
/// can end silently.
///
/// Threading: thread-safe. Channels are called on the caller's thread and must not block for
/// long (issue 7's network channels queue and deliver on their own thread).
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/journal.hpp"

#include <nlohmann/json.hpp>

#include <functional>
#include <mutex>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// A station event for listeners (the web page's event stream, tests).
struct StationEvent {
    std::string type; ///< section_captured, section_registered, section_damaged, run_state,
                      ///< alert_raised, alert_acknowledged
    nlohmann::json data;
};

class Notifier {
public:
    explicit Notifier(Journal& journal) : journal_(journal) {}

    using AlertChannel = std::function<void(const AlertRecord&)>;
    using EventListener = std::function<void(const StationEvent&)>;
    void addChannel(AlertChannel channel);
    void addListener(EventListener listener);

    /// Stores and delivers an alert. \return its id, or the journal's error (then the alert is
    /// still logged and delivered: a full disk must not swallow the "low disk" alert).
    core::Result<std::int64_t> raise(const std::string& kind, const std::string& severity,
                                     const std::string& message,
                                     std::optional<std::int64_t> runId = std::nullopt,
                                     std::optional<std::int64_t> sectionId = std::nullopt);
    /// Journals the run's new state and raises the matching alert for paused, finished, failed
    /// and cancelled runs.
    core::Result<void> runStateChanged(std::int64_t runId, RunState state, const std::string& reason);
    core::Result<AlertRecord> acknowledge(std::int64_t alertId, const std::string& action);
    /// Tells listeners (no alert, nothing stored).
    void publish(const StationEvent& event);

private:
    Journal& journal_;
    std::mutex mutex_;
    std::vector<AlertChannel> channels_;
    std::vector<EventListener> listeners_;
};

} // namespace slicestation::daemon
