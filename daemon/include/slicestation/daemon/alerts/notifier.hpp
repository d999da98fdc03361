#pragma once
/// The one place alerts and run-state events go through. Every alert is stored in the journal
/// first (it stays open until acknowledged), then logged once on stderr (the systemd journal
/// captures it) and handed to every registered channel.
///
/// An alert the journal cannot store (disk full: SQLITE_FULL) is not lost: it is logged,
/// delivered to the channels and the event stream at once like any other, and held in memory
/// (with a negative id, at most kMaxHeldAlerts, oldest dropped first; one alert equal in kind,
/// run, section and message to one already held is not held twice). storeHeldAlerts() stores
/// the held alerts, oldest first, with their original raised time; it runs before every
/// raise() and the scan loop calls it about once a second, so they reach the journal as soon as
/// there is space (each stored one is announced as an `alert_stored` event). Every terminal state
/// of a run (finished, paused, failed, cancelled) is reported through runStateChanged(), so no
/// abort path can end silently.
///
/// Threading: thread-safe. Channels are called on the caller's thread and must not block for
/// long (issue 7's network channels queue and deliver on their own thread).
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <nlohmann/json.hpp>

#include <functional>
#include <mutex>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// A station event for listeners (the web page's event stream, tests).
struct StationEvent {
    std::string type; ///< section_captured, section_registered, section_damaged, run_state,
                      ///< stage_position (while moving, <= 5 Hz, and where a move ended),
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
    core::Result<std::int64_t> raise(AlertKind kind, AlertSeverity severity,
                                     const std::string& message,
                                     std::optional<std::int64_t> runId = std::nullopt,
                                     std::optional<std::int64_t> sectionId = std::nullopt);
    /// Journals the run's new state and raises the matching alert for paused, finished, failed
    /// and cancelled runs. When the journal cannot store the state (disk full), the alert is
    /// raised all the same (held, see above) and the journal's error returned; the run_state
    /// event is published only for a stored state.
    core::Result<void> runStateChanged(std::int64_t runId, RunState state,
                                       const std::string& reason);
    core::Result<AlertRecord> acknowledge(std::int64_t alertId, const std::string& action);

    static constexpr std::size_t kMaxHeldAlerts = 100;
    /// The alerts raised but not yet stored, oldest first (ids negative).
    std::vector<AlertRecord> heldAlerts() const;
    /// Tries to store the held alerts, oldest first; stops at the first the journal refuses.
    /// \return how many are still held.
    std::size_t storeHeldAlerts();
    /// Tells listeners (no alert, nothing stored).
    void publish(const StationEvent& event);

private:
    Journal& journal_;
    mutable std::mutex mutex_;
    mutable std::mutex heldMutex_; ///< guards held_ and nextHeldId_; taken before mutex_
    std::vector<AlertRecord> held_;
    std::int64_t nextHeldId_ = -1;
    std::vector<AlertChannel> channels_;
    std::vector<EventListener> listeners_;
};

} // namespace slicestation::daemon
