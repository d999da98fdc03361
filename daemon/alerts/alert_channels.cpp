#include "slicestation/daemon/alerts/alert_channels.hpp"

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
#include <map>
#include <optional>
#include <initializer_list>
#include <string_view>
#include <thread>

extern char** environ; // NOLINT(readability-redundant-declaration): POSIX declares it nowhere

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using Clock = std::chrono::steady_clock;

namespace {

constexpr const char* kSeverities[] = {"info", "warning", "critical"};

struct ParsedUrl {
    std::string scheme; ///< http or https
    std::string host;   ///< as written, [brackets] kept for IPv6
    int port = 0;
    std::string path; ///< at least "/", query included
    /// scheme://host:port, what httplib::Client takes.
    std::string base() const { return scheme + "://" + host + ":" + std::to_string(port); }
    /// For logs and stats: the path of a webhook URL often is its secret (Slack, Mattermost).
    std::string redacted() const {
        return scheme + "://" + host + ":" + std::to_string(port) + (path == "/" ? "/" : "/...");
    }
};

Result<ParsedUrl> parseUrl(const std::string& url) {
    const auto bad = [&](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "\"" + url + "\": " + what);
    };
    ParsedUrl u;
    std::string rest;
    if (url.starts_with("http://")) {
        u.scheme = "http";
        u.port = 80;
        rest = url.substr(7);
    } else if (url.starts_with("https://")) {
        u.scheme = "https";
        u.port = 443;
        rest = url.substr(8);
    } else {
        return bad("expected http://host[:port][/path] or https://...");
    }
    if (std::any_of(url.begin(), url.end(), [](char c) { return c <= ' ' || c == 0x7f; }))
        return bad("contains white space or control characters");
    const auto slash = rest.find_first_of("/?#");
    std::string authority = rest.substr(0, slash);
    u.path = slash == std::string::npos ? "/" : rest.substr(slash);
    if (!u.path.starts_with("/"))
        u.path = "/" + u.path;
    if (const auto hash = u.path.find('#'); hash != std::string::npos)
        u.path.resize(hash);
    if (authority.find('@') != std::string::npos)
        return bad("user:password@ in the URL is not supported");
    std::string portText;
    if (authority.starts_with("[")) {
        const auto close = authority.find(']');
        if (close == std::string::npos)
            return bad("unterminated [IPv6 address]");
        u.host = authority.substr(0, close + 1);
        const std::string after = authority.substr(close + 1);
        if (!after.empty()) {
            if (!after.starts_with(":"))
                return bad("expected :port after the IPv6 address");
            portText = after.substr(1);
        }
        if (u.host.size() < 3 ||
            u.host.find_first_not_of("0123456789abcdefABCDEF:.", 1) != u.host.size() - 1)
            return bad("bad IPv6 address " + u.host);
    } else {
        const auto colon = authority.find(':');
        u.host = authority.substr(0, colon);
        if (colon != std::string::npos)
            portText = authority.substr(colon + 1);
        if (u.host.empty())
            return bad("no host");
        if (!std::all_of(u.host.begin(), u.host.end(), [](char c) {
                return std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '-' ||
                       c == '_';
            }))
            return bad("bad host name \"" + u.host + "\"");
    }
    if (!portText.empty() || authority.ends_with(":")) {
        if (portText.empty() || portText.size() > 5 ||
            !std::all_of(portText.begin(), portText.end(),
                         [](char c) { return c >= '0' && c <= '9'; }))
            return bad("bad port \"" + portText + "\"");
        u.port = std::stoi(portText);
        if (u.port < 1 || u.port > 65535)
            return bad("port " + portText + " is outside 1..65535");
    }
    return u;
}

std::string describe(httplib::Error e) {
    switch (e) {
    case httplib::Error::Connection:
        return "cannot connect";
    case httplib::Error::ConnectionTimeout:
        return "connect timed out";
    case httplib::Error::Read:
        return "no answer in time, or the connection was closed";
    case httplib::Error::Write:
        return "sending the request failed";
    case httplib::Error::SSLConnection:
        return "TLS handshake failed";
    case httplib::Error::SSLLoadingCerts:
        return "cannot load the system's CA certificates";
    case httplib::Error::SSLServerVerification:
        return "the server's certificate was not accepted";
    default:
        return httplib::to_string(e);
    }
}

std::string hostName() {
    char buf[256] = {};
    if (gethostname(buf, sizeof buf - 1) != 0)
        return "unknown";
    return buf;
}

std::string commandLine(const std::vector<std::string>& argv) {
    std::string s;
    for (const auto& a : argv) {
        if (!s.empty())
            s += ' ';
        s += a;
    }
    if (s.size() > 120)
        s = s.substr(0, 117) + "...";
    return s;
}

std::string optionalId(const std::optional<std::int64_t>& id) {
    return id ? std::to_string(*id) : std::string();
}

/// Walks the [[alerts.<name>]] tables (absent: none): each must be a table with only `known`
/// keys, and `each(table, path)` reads it.
template <class Each>
Result<void> forEachTable(const nlohmann::json& alerts, const std::string& name,
                          std::initializer_list<std::string_view> known, const FieldReader& rd, Each each) {
    if (!alerts.contains(name))
        return {};
    const auto& list = alerts[name];
    const std::string path = "alerts." + name;
    if (!list.is_array())
        return rd.bad(path, "expected [[" + path + "]] tables");
    for (std::size_t i = 0; i < list.size(); ++i) {
        const std::string p = path + "[" + std::to_string(i) + "]";
        const auto& e = list[i];
        if (!e.is_object())
            return rd.bad(p, "expected a table");
        if (auto keys = rd.onlyKeys(e, p, known); !keys)
            return keys.error();
        if (auto read = each(e, p); !read)
            return read.error();
    }
    return {};
}

} // namespace

// Settings -------------------------------------------------------------------------------------

int severityRank(const std::string& severity) noexcept {
    if (severity == "info")
        return 0;
    if (severity == "warning")
        return 1;
    return 2;
}

Result<AlertSettings> parseAlertSettings(const nlohmann::json& station, const std::string& origin) {
    FieldReader rd(origin);
    AlertSettings s;
    if (!station.is_object() || !station.contains("alerts"))
        return s;
    const nlohmann::json& t = station["alerts"];
    if (!t.is_object())
        return rd.bad("alerts", "expected a table [alerts]");
    if (auto keys = rd.onlyKeys(t, "alerts",
                              {"journal", "retries", "backoff_initial_ms", "backoff_max_ms",
                               "max_per_minute", "min_severity", "webhook", "command"});
        !keys)
        return keys.error();

    auto journal = rd.boolean(t, "alerts", "journal", true);
    if (!journal)
        return journal.error();
    s.journal = *journal;
    auto retries = rd.integer(t, "alerts", "retries", 4, 0, 100);
    if (!retries)
        return retries.error();
    s.retries = static_cast<int>(*retries);
    auto bi = rd.integer(t, "alerts", "backoff_initial_ms", 1000, 1, 3'600'000);
    if (!bi)
        return bi.error();
    s.backoffInitial = std::chrono::milliseconds(*bi);
    auto bm = rd.integer(t, "alerts", "backoff_max_ms", 60'000, 1, 86'400'000);
    if (!bm)
        return bm.error();
    if (*bm < *bi)
        return rd.bad("alerts.backoff_max_ms", "must not be less than backoff_initial_ms");
    s.backoffMax = std::chrono::milliseconds(*bm);
    auto mpm = rd.integer(t, "alerts", "max_per_minute", 20, 0, 100'000);
    if (!mpm)
        return mpm.error();
    s.maxPerWindow = static_cast<int>(*mpm);
    auto sev = rd.string(t, "alerts", "min_severity", std::string("info"));
    if (!sev)
        return sev.error();
    if (std::none_of(std::begin(kSeverities), std::end(kSeverities),
                     [&](const char* k) { return *sev == k; }))
        return rd.bad("alerts.min_severity",
                      "expected \"info\", \"warning\" or \"critical\", got \"" + *sev + "\"");
    s.minSeverity = *sev;

    const auto timeout = [&](const nlohmann::json& e, const std::string& p,
                             double fallback) -> Result<std::chrono::milliseconds> {
        auto v = rd.number(e, p, "timeout_s", fallback, 0.01, 3600);
        if (!v)
            return v.error();
        return std::chrono::milliseconds(std::llround(*v * 1000));
    };
    auto webhooks = forEachTable(
        t, "webhook", {"url", "format", "timeout_s"}, rd,
        [&](const nlohmann::json& e, const std::string& p) -> Result<void> {
            WebhookSettings w;
            auto url = rd.string(e, p, "url", std::nullopt);
            if (!url)
                return url.error();
            auto parsed = parseUrl(*url);
            if (!parsed)
                return rd.bad(p + ".url", parsed.error().message);
#ifndef CPPHTTPLIB_OPENSSL_SUPPORT
            if (parsed->scheme == "https")
                return rd.bad(
                    p + ".url",
                    "https is not available: cpp-httplib was built without TLS; use http://");
#endif
            w.url = *url;
            auto format = rd.string(e, p, "format", std::string("json"));
            if (!format)
                return format.error();
            if (*format == "json")
                w.format = WebhookSettings::Format::Json;
            else if (*format == "slack")
                w.format = WebhookSettings::Format::Slack;
            else
                return rd.bad(p + ".format",
                              "expected \"json\" or \"slack\", got \"" + *format + "\"");
            auto to = timeout(e, p, 5);
            if (!to)
                return to.error();
            w.timeout = *to;
            s.webhooks.push_back(std::move(w));
            return {};
        });
    if (!webhooks)
        return webhooks.error();
    auto commands = forEachTable(
        t, "command", {"argv", "timeout_s"}, rd,
        [&](const nlohmann::json& e, const std::string& p) -> Result<void> {
            CommandSettings c;
            if (!e.contains("argv"))
                return rd.bad(p + ".argv", "missing");
            const auto& argv = e["argv"];
            if (!argv.is_array() ||
                !std::all_of(argv.begin(), argv.end(), [](const auto& a) { return a.is_string(); }))
                return rd.bad(p + ".argv", "expected an array of strings, got " + argv.dump());
            if (argv.empty())
                return rd.bad(p + ".argv", "empty: name the program to run");
            for (const auto& a : argv)
                c.argv.push_back(a.get<std::string>());
            if (c.argv[0].empty())
                return rd.bad(p + ".argv", "the program name (argv[0]) is empty");
            auto to = timeout(e, p, 10);
            if (!to)
                return to.error();
            c.timeout = *to;
            s.commands.push_back(std::move(c));
            return {};
        });
    if (!commands)
        return commands.error();
    return s;
}

// Webhook --------------------------------------------------------------------------------------

struct WebhookSink::Impl {
    WebhookSettings settings;
    ParsedUrl url;
    std::string station = hostName();
    std::mutex mutex;
    httplib::Client* current = nullptr; ///< the request in flight, for cancel()
    bool cancelled = false;
};

WebhookSink::WebhookSink(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
WebhookSink::~WebhookSink() = default;

Result<std::unique_ptr<WebhookSink>> WebhookSink::create(WebhookSettings settings) {
    auto url = parseUrl(settings.url);
    if (!url)
        return url.error();
#ifndef CPPHTTPLIB_OPENSSL_SUPPORT
    if (url->scheme == "https")
        return makeError(ErrorCode::Unsupported,
                         "webhook " + settings.url + ": https needs cpp-httplib with TLS");
#endif
    auto impl = std::make_unique<Impl>();
    impl->settings = std::move(settings);
    impl->url = *url;
    return std::unique_ptr<WebhookSink>(new WebhookSink(std::move(impl)));
}

std::string WebhookSink::name() const {
    return "webhook " + impl_->url.redacted();
}

std::string WebhookSink::body(const AlertRecord& alert) const {
    if (impl_->settings.format == WebhookSettings::Format::Slack) {
        std::string text = "[" + alert.severity + "] " + alert.kind + ": " + alert.message;
        if (alert.runId && alert.sectionId)
            text += " (run " + std::to_string(*alert.runId) + ", section " +
                    std::to_string(*alert.sectionId) + ")";
        else if (alert.runId)
            text += " (run " + std::to_string(*alert.runId) + ")";
        else if (alert.sectionId)
            text += " (section " + std::to_string(*alert.sectionId) + ")";
        return nlohmann::json{{"text", text}}.dump();
    }
    nlohmann::json j = toJson(alert);
    j["station"] = impl_->station;
    return j.dump();
}

Result<void> WebhookSink::deliver(const AlertRecord& alert) {
    const std::string what = name();
    {
        std::lock_guard lock(impl_->mutex);
        if (impl_->cancelled)
            return makeError(ErrorCode::Cancelled, what + ": stopped");
    }
    httplib::Client client(impl_->url.base());
    const auto timeout = impl_->settings.timeout;
    client.set_connection_timeout(timeout);
    client.set_read_timeout(timeout);
    client.set_write_timeout(timeout);
    client.set_follow_location(false);
    client.set_default_headers({{"User-Agent", "slicestationd"}});
    {
        std::lock_guard lock(impl_->mutex);
        impl_->current = &client;
    }
    const std::string payload = body(alert);
    auto res = client.Post(impl_->url.path, payload, "application/json");
    bool cancelled = false;
    {
        std::lock_guard lock(impl_->mutex);
        impl_->current = nullptr;
        cancelled = impl_->cancelled;
    }
    if (cancelled)
        return makeError(ErrorCode::Cancelled, what + ": stopped");
    if (!res) {
        const auto err = res.error();
        const auto code = err == httplib::Error::Read || err == httplib::Error::ConnectionTimeout
                              ? ErrorCode::Timeout
                              : ErrorCode::Disconnected;
        return makeError(code, what + ": no response: " + describe(err));
    }
    if (res->status < 200 || res->status > 299) {
        std::string snippet = res->body.substr(0, 200);
        return makeError(ErrorCode::IoError, what + ": HTTP status " + std::to_string(res->status) +
                                                 (snippet.empty() ? "" : ": " + snippet));
    }
    return {};
}

void WebhookSink::cancel() noexcept {
    std::lock_guard lock(impl_->mutex);
    impl_->cancelled = true;
    if (impl_->current)
        impl_->current->stop();
}

// Command --------------------------------------------------------------------------------------

struct CommandSink::Impl {
    CommandSettings settings;
    core::UniqueFd cancelFd; ///< eventfd, readable once cancelled: wakes the wait for the child
    std::atomic<bool> cancelled{false};
};

CommandSink::CommandSink(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
CommandSink::~CommandSink() = default;

Result<std::unique_ptr<CommandSink>> CommandSink::create(CommandSettings settings) {
    if (settings.argv.empty() || settings.argv[0].empty())
        return makeError(ErrorCode::InvalidArgument, "command: empty argv");
    auto impl = std::make_unique<Impl>();
    impl->settings = std::move(settings);
    impl->cancelFd.reset(eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK));
    if (!impl->cancelFd)
        return makeError(ErrorCode::Internal,
                         "command: eventfd: " + std::string(std::strerror(errno)), errno);
    return std::unique_ptr<CommandSink>(new CommandSink(std::move(impl)));
}

std::string CommandSink::name() const {
    return "command " + commandLine(impl_->settings.argv);
}

void CommandSink::cancel() noexcept {
    impl_->cancelled = true;
    const std::uint64_t one = 1;
    (void)!write(impl_->cancelFd.get(), &one, sizeof one);
}

Result<void> CommandSink::deliver(const AlertRecord& alert) {
    const std::string what = name();
    if (impl_->cancelled)
        return makeError(ErrorCode::Cancelled, what + ": stopped");

    // The daemon's environment, minus stale SLST_ALERT_* entries, plus this alert.
    std::vector<std::string> env;
    for (char** e = environ; e && *e; ++e)
        if (!std::string_view(*e).starts_with("SLST_ALERT_"))
            env.emplace_back(*e);
    env.push_back("SLST_ALERT_ID=" + std::to_string(alert.id));
    env.push_back("SLST_ALERT_KIND=" + alert.kind);
    env.push_back("SLST_ALERT_SEVERITY=" + alert.severity);
    env.push_back("SLST_ALERT_MESSAGE=" + alert.message);
    env.push_back("SLST_ALERT_RUN_ID=" + optionalId(alert.runId));
    env.push_back("SLST_ALERT_SECTION_ID=" + optionalId(alert.sectionId));
    env.push_back("SLST_ALERT_RAISED_UTC=" + alert.raisedUtc);
    env.push_back("SLST_ALERT_JSON=" + toJson(alert).dump());
    std::vector<char*> envp, argvp;
    for (auto& e : env)
        envp.push_back(e.data());
    envp.push_back(nullptr);
    std::vector<std::string> argv = impl_->settings.argv;
    for (auto& a : argv)
        argvp.push_back(a.data());
    argvp.push_back(nullptr);

    posix_spawn_file_actions_t actions;
    posix_spawnattr_t attr;
    posix_spawn_file_actions_init(&actions);
    posix_spawnattr_init(&attr);
    posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null", O_RDONLY, 0);
    // The daemon blocks SIGTERM/SIGINT in every thread and ignores SIGPIPE; a child inherits
    // both, so it gets a clean mask and default dispositions. Its own process group lets a
    // timeout kill whatever it started too.
    sigset_t none, defaults;
    sigemptyset(&none);
    sigemptyset(&defaults);
    for (int sig : {SIGPIPE, SIGTERM, SIGINT, SIGHUP, SIGQUIT, SIGCHLD})
        sigaddset(&defaults, sig);
    posix_spawnattr_setsigmask(&attr, &none);
    posix_spawnattr_setsigdefault(&attr, &defaults);
    posix_spawnattr_setpgroup(&attr, 0);
    posix_spawnattr_setflags(
        &attr,
        static_cast<short>(POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETSIGDEF | POSIX_SPAWN_SETPGROUP));
    pid_t pid = -1;
    const bool hasSlash = argv[0].find('/') != std::string::npos;
    const int rc = hasSlash
                       ? posix_spawn(&pid, argvp[0], &actions, &attr, argvp.data(), envp.data())
                       : posix_spawnp(&pid, argvp[0], &actions, &attr, argvp.data(), envp.data());
    posix_spawn_file_actions_destroy(&actions);
    posix_spawnattr_destroy(&attr);
    if (rc != 0)
        return makeError(rc == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                         what + ": cannot start: " + std::strerror(rc), rc);

    // glibc 2.36's <sys/pidfd.h> lacks extern "C", so the system call is made directly.
    core::UniqueFd pidFd(static_cast<int>(syscall(SYS_pidfd_open, pid, 0)));
    const auto deadline = Clock::now() + impl_->settings.timeout;
    int status = 0;
    bool timedOut = false, cancelled = false;
    for (;;) {
        const pid_t w = waitpid(pid, &status, WNOHANG);
        if (w == pid)
            break;
        if (w < 0 && errno != EINTR)
            return makeError(ErrorCode::Internal, what + ": waitpid: " + std::strerror(errno),
                             errno);
        const auto now = Clock::now();
        timedOut = now >= deadline;
        cancelled = impl_->cancelled;
        if (timedOut || cancelled) {
            kill(-pid, SIGKILL);
            kill(pid, SIGKILL);
            while (waitpid(pid, &status, 0) < 0 && errno == EINTR) {
            }
            break;
        }
        auto left =
            std::chrono::duration_cast<std::chrono::milliseconds>(deadline - now).count() + 1;
        // Without a pidfd (old kernel) the child is polled.
        if (!pidFd)
            left = std::min<long long>(left, 20);
        pollfd fds[2] = {{impl_->cancelFd.get(), POLLIN, 0}, {pidFd.get(), POLLIN, 0}};
        (void)poll(fds, pidFd ? 2 : 1, static_cast<int>(std::min<long long>(left, 60'000)));
    }
    const auto seconds = [](std::chrono::milliseconds d) {
        char buf[32];
        std::snprintf(buf, sizeof buf, "%g s", static_cast<double>(d.count()) / 1000.0);
        return std::string(buf);
    };
    if (cancelled)
        return makeError(ErrorCode::Cancelled, what + ": stopped: killed");
    if (timedOut)
        return makeError(ErrorCode::Timeout, what + ": did not finish within " +
                                                 seconds(impl_->settings.timeout) + ": killed");
    if (WIFEXITED(status) && WEXITSTATUS(status) == 0)
        return {};
    if (WIFEXITED(status))
        return makeError(ErrorCode::IoError,
                         what + ": exited with status " + std::to_string(WEXITSTATUS(status)));
    if (WIFSIGNALED(status))
        return makeError(ErrorCode::IoError, what + ": killed by signal " +
                                                 std::to_string(WTERMSIG(status)) + " (" +
                                                 strsignal(WTERMSIG(status)) + ")");
    return makeError(ErrorCode::IoError,
                     what + ": ended with wait status " + std::to_string(status));
}

// Journal --------------------------------------------------------------------------------------

JournalSink::JournalSink(Send send) : send_(std::move(send)) {
    if (!send_)
        send_ = [](const std::vector<std::string>& fields) {
            std::vector<iovec> iov;
            iov.reserve(fields.size());
            for (const auto& f : fields)
                iov.push_back({const_cast<char*>(f.data()), f.size()});
            return sd_journal_sendv(iov.data(), static_cast<int>(iov.size()));
        };
}

std::vector<std::string> JournalSink::fields(const AlertRecord& alert) {
    const int rank = severityRank(alert.severity);
    const int priority = rank == 0 ? 5 : rank == 1 ? 4 : 2; // notice, warning, critical
    std::vector<std::string> f{"MESSAGE=ALERT " + alert.kind + ": " + alert.message,
                               "PRIORITY=" + std::to_string(priority),
                               "SYSLOG_IDENTIFIER=slicestationd",
                               "SLST_ALERT_ID=" + std::to_string(alert.id),
                               "SLST_ALERT_KIND=" + alert.kind,
                               "SLST_ALERT_SEVERITY=" + alert.severity};
    if (alert.runId)
        f.push_back("SLST_RUN_ID=" + std::to_string(*alert.runId));
    if (alert.sectionId)
        f.push_back("SLST_SECTION_ID=" + std::to_string(*alert.sectionId));
    return f;
}

Result<void> JournalSink::deliver(const AlertRecord& alert) {
    const int rc = send_(fields(alert));
    if (rc < 0)
        return makeError(ErrorCode::IoError,
                         "journal: sd_journal_sendv: " + std::string(std::strerror(-rc)), -rc);
    return {};
}

Result<std::vector<std::unique_ptr<AlertChannelSink>>>
makeAlertSinks(const AlertSettings& settings, JournalSink::Send journalSend) {
    std::vector<std::unique_ptr<AlertChannelSink>> sinks;
    if (settings.journal)
        sinks.push_back(std::make_unique<JournalSink>(std::move(journalSend)));
    for (const auto& w : settings.webhooks) {
        auto sink = WebhookSink::create(w);
        if (!sink)
            return sink.error();
        sinks.push_back(std::move(*sink));
    }
    for (const auto& c : settings.commands) {
        auto sink = CommandSink::create(c);
        if (!sink)
            return sink.error();
        sinks.push_back(std::move(*sink));
    }
    return sinks;
}

// Dispatcher -----------------------------------------------------------------------------------

struct AlertDispatcher::Lane {
    std::unique_ptr<AlertChannelSink> sink;
    std::deque<AlertRecord> queue;
    std::deque<Clock::time_point> starts; ///< first attempts inside the rate window
    std::uint64_t heldCount = 0;          ///< alerts over the rate limit, not yet summarised
    std::map<std::string, std::uint64_t> heldKinds;
    int heldRank = 0;
    bool busy = false; ///< delivering or waiting to retry
    bool done = false; ///< the worker has returned
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
      minRank_(severityRank(policy.minSeverity)), onGiveUp_(std::move(onGiveUp)) {
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
    if (severityRank(alert.severity) < minRank_)
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
                ++lane.heldKinds[a.kind];
                lane.heldRank = std::max(lane.heldRank, severityRank(a.severity));
                ++lane.stats.suppressed;
            }
            lane.queue.clear();
        }
        std::optional<AlertRecord> next;
        // Held alerts go out as one summary once the window has room, or at once when stopping.
        if (lane.heldCount > 0 && (room || stopping_)) {
            AlertRecord s;
            s.kind = "alert_summary";
            s.severity = kSeverities[std::clamp(lane.heldRank, 0, 2)];
            s.raisedUtc = Journal::nowUtc();
            std::string kinds;
            for (const auto& [kind, n] : lane.heldKinds)
                kinds += (kinds.empty() ? "" : ", ") + kind +
                         (n > 1 ? " (x" + std::to_string(n) + ")" : "");
            s.message = std::to_string(lane.heldCount) + " more alerts: kinds " + kinds +
                        "; held by the rate limit of this channel, see slicectl alerts";
            lane.heldCount = 0;
            lane.heldKinds.clear();
            lane.heldRank = 0;
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
