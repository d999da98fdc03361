#pragma once
/// Outward delivery of alerts (issue 7): the `[alerts]` table of the station file, the channels
/// an alert can leave the machine through (webhook, command, systemd journal), and the
/// dispatcher that queues, retries, rate-limits and summarises per channel.
///
/// The Notifier stores every alert before it reaches a channel, so a channel that fails loses
/// nothing: the alert stays open in the journal until acknowledged. Delivery is best effort.
///
/// The settings, the channel interface, its three models and the dispatcher live in this one
/// header because they are one feature with one configuration table.
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <nlohmann/json.hpp>

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// One `[[alerts.webhook]]` entry.
struct WebhookSettings {
    enum class Format {
        Json,  ///< toJson(alert) plus "station" (the host name)
        Slack, ///< Slack/Mattermost incoming webhook: {"text": "[severity] kind: message (...)"}
    };
    std::string url; ///< http://host[:port][/path] or https://...
    Format format = Format::Json;
    std::chrono::milliseconds timeout{5000}; ///< connect, send and receive, each
};

/// One `[[alerts.command]]` entry.
struct CommandSettings {
    std::vector<std::string> argv;             ///< argv[0] is looked up in PATH when it has no '/'
    std::chrono::milliseconds timeout{10'000}; ///< the child is killed (SIGKILL) after this
};

/// The `[alerts]` table. Every limit applies to each channel on its own.
struct AlertSettings {
    bool journal = true; ///< one structured systemd-journal entry per alert
    int retries = 4;     ///< delivery attempts after the first
    std::chrono::milliseconds backoffInitial{1000}; ///< wait after the first failure, then doubled
    std::chrono::milliseconds backoffMax{60'000};   ///< cap of the doubled wait
    int maxPerWindow = 20;                          ///< `max_per_minute`; 0: no limit
    /// The sliding window of the rate limit. Not a file key (always a minute there); tests
    /// shorten it.
    std::chrono::milliseconds rateWindow{60'000};
    AlertSeverity minSeverity = AlertSeverity::Info; ///< lower ones are not sent
    std::size_t queueCapacity = 1000; ///< per channel; when full the oldest alert is dropped
    std::vector<WebhookSettings> webhooks;
    std::vector<CommandSettings> commands;
};

/// Parses `station["alerts"]` (absent: the defaults, journal only). Unknown keys, a bad URL (or
/// https without TLS support in cpp-httplib), an empty argv, a bad format or severity are
/// InvalidArgument naming the key, e.g. `station.toml: alerts.webhook[0].url: ...`.
[[nodiscard]] core::Result<AlertSettings> parseAlertSettings(const nlohmann::json& station,
                                                             const std::string& origin);

/// Where an alert goes: one configured webhook, command or the journal.
/// Threading: deliver() is called from one thread at a time (the channel's worker); cancel()
/// may be called from any thread while deliver() runs.
class AlertChannelSink {
public:
    virtual ~AlertChannelSink() = default;
    /// Names the channel in stats and messages, e.g. "webhook http://host:9000/..." (a webhook
    /// path is left out: it often is the secret).
    virtual std::string name() const = 0;
    /// Delivers one alert once (no retries: the dispatcher retries). Blocks for at most the
    /// channel's own timeout. \return an error naming the URL/command and the status;
    /// Cancelled after cancel().
    [[nodiscard]] virtual core::Result<void> deliver(const AlertRecord& alert) = 0;
    /// Whether the dispatcher retries a failed delivery (default true).
    virtual bool retryFailures() const noexcept { return true; }
    /// Preempts a deliver() in progress and makes later ones return Cancelled at once. Idempotent,
    /// does not block.
    virtual void cancel() noexcept {}
};

/// POSTs the alert with cpp-httplib. A connection error or a non-2xx status is an error
/// (Disconnected / Timeout / IoError) naming the URL and the status.
class WebhookSink final : public AlertChannelSink {
public:
    /// InvalidArgument for a URL that is not http(s)://host[:port][/path], Unsupported for https
    /// when cpp-httplib has no TLS.
    [[nodiscard]] static core::Result<std::unique_ptr<WebhookSink>>
    create(WebhookSettings settings);
    ~WebhookSink() override;
    std::string name() const override;
    core::Result<void> deliver(const AlertRecord& alert) override;
    void cancel() noexcept override;

    /// The request body this sink sends (public for tests).
    std::string body(const AlertRecord& alert) const;

private:
    struct Impl;
    explicit WebhookSink(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
};

/// Runs a command per alert (posix_spawn) with stdin on /dev/null, stdout and stderr inherited,
/// default signal dispositions and an empty signal mask, in its own process group, and the
/// daemon's environment plus SLST_ALERT_ID, SLST_ALERT_KIND, SLST_ALERT_SEVERITY,
/// SLST_ALERT_MESSAGE, SLST_ALERT_RUN_ID, SLST_ALERT_SECTION_ID (empty when none),
/// SLST_ALERT_RAISED_UTC and SLST_ALERT_JSON. A non-zero exit, a signal or the timeout (the
/// process group is killed and the child reaped) is an error naming the command and status.
class CommandSink final : public AlertChannelSink {
public:
    /// InvalidArgument for an empty argv; Internal when no eventfd can be made.
    [[nodiscard]] static core::Result<std::unique_ptr<CommandSink>>
    create(CommandSettings settings);
    ~CommandSink() override;
    std::string name() const override;
    core::Result<void> deliver(const AlertRecord& alert) override;
    void cancel() noexcept override;

private:
    struct Impl;
    explicit CommandSink(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
};

/// One structured systemd-journal entry per alert: MESSAGE, PRIORITY (critical 2, warning 4,
/// info 5), SYSLOG_IDENTIFIER=slicestationd, SLST_ALERT_ID, SLST_ALERT_KIND, SLST_ALERT_SEVERITY,
/// and SLST_RUN_ID / SLST_SECTION_ID when the alert has them. Without journald the send fails
/// (IoError with its errno) and is not retried: a local socket that is absent now will not
/// appear within a backoff, and the Notifier has already logged the alert on stderr.
class JournalSink final : public AlertChannelSink {
public:
    /// Sends "FIELD=value" strings; returns 0 or a negative errno (as sd_journal_sendv does).
    using Send = std::function<int(const std::vector<std::string>& fields)>;
    /// `send` defaults to sd_journal_sendv.
    explicit JournalSink(Send send = {});
    std::string name() const override { return "journal"; }
    bool retryFailures() const noexcept override { return false; }
    core::Result<void> deliver(const AlertRecord& alert) override;
    /// The fields deliver() sends (public for tests).
    static std::vector<std::string> fields(const AlertRecord& alert);

private:
    Send send_;
};

/// Builds the sinks `settings` configures: the journal first (when enabled, with `journalSend`
/// or sd_journal_sendv), then webhooks, then commands, in file order.
[[nodiscard]] core::Result<std::vector<std::unique_ptr<AlertChannelSink>>>
makeAlertSinks(const AlertSettings& settings, JournalSink::Send journalSend = {});

/// What one channel did since the dispatcher started.
struct AlertChannelStats {
    std::string name;
    std::uint64_t delivered = 0;  ///< alerts and summaries that arrived
    std::uint64_t failed = 0;     ///< gave up after all attempts (or at stop)
    std::uint64_t retried = 0;    ///< attempts after a failed one
    std::uint64_t suppressed = 0; ///< alerts over the rate limit, folded into a summary
    std::uint64_t summaries = 0;  ///< summary alerts made
    std::uint64_t dropped = 0;    ///< queue overflow, or left undelivered at stop
    std::string lastError;
};

/// Queues alerts and delivers them on one worker thread per channel, so a slow or dead channel
/// never delays another. Per channel: a bounded queue (overflow drops the oldest), up to
/// `retries` more attempts with exponential backoff, and a sliding-window rate limit: alerts
/// over `maxPerWindow` are held and sent as one summary alert (kind "alert_summary", message
/// "N more alerts: kinds ...") once the window has room again.
///
/// Threading: post(), stats(), waitIdle() and stop() are thread-safe. post() only takes a mutex.
class AlertDispatcher {
public:
    /// Called on a worker thread when a channel gives up on an alert (for the daemon's log).
    using GiveUp = std::function<void(const std::string& channel, const AlertRecord& alert,
                                      const core::Error& error)>;

    /// Starts one worker per sink. Only retries, backoff*, maxPerWindow, rateWindow, minSeverity
    /// and queueCapacity of `policy` are used.
    AlertDispatcher(const AlertSettings& policy,
                    std::vector<std::unique_ptr<AlertChannelSink>> sinks, GiveUp onGiveUp = {});
    /// stop(0).
    ~AlertDispatcher();
    AlertDispatcher(const AlertDispatcher&) = delete;
    AlertDispatcher& operator=(const AlertDispatcher&) = delete;

    /// Queues `alert` for every channel unless it is below minSeverity. Ignored after stop().
    void post(const AlertRecord& alert);
    /// Names of the channels, in order.
    std::vector<std::string> channelNames() const;
    std::vector<AlertChannelStats> stats() const;
    /// Blocks until every queue is empty, nothing is held or being delivered, or `timeout`.
    /// \return true when idle.
    bool waitIdle(std::chrono::milliseconds timeout) const;
    /// Stops taking alerts, delivers what it can within `drainTimeout` (held alerts go out at
    /// once as a summary; backoff waits end at the deadline), then cancels deliveries still in
    /// progress and joins the workers. Returns within about `drainTimeout`. Idempotent.
    void stop(std::chrono::milliseconds drainTimeout) noexcept;

private:
    struct Lane;
    void run(Lane& lane);
    void deliverWithRetries(Lane& lane, const AlertRecord& alert,
                            std::unique_lock<std::mutex>& lock);
    bool idleLocked() const;

    int retries_;
    std::chrono::milliseconds backoffInitial_, backoffMax_, rateWindow_;
    std::size_t maxPerWindow_, queueCapacity_;
    AlertSeverity minSeverity_;
    GiveUp onGiveUp_;

    mutable std::mutex mutex_;
    mutable std::condition_variable cv_;
    bool stopping_ = false;
    std::chrono::steady_clock::time_point deadline_;
    std::vector<std::unique_ptr<Lane>> lanes_;
    std::mutex joinMutex_;
};

} // namespace slicestation::daemon
