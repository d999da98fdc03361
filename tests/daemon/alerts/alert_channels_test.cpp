// Alert channels against real receivers: an httplib server on 127.0.0.1, /bin/sh commands, and
// an injected journal sender. Backoffs and the rate window are shortened so the suite is fast.
#include "slicestation/core/unique_fd.hpp"
#include "slicestation/daemon/alerts/alert_channels.hpp"
#include "slicestation/daemon/config/config_document.hpp"

#include <gtest/gtest.h>
#include <httplib.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <pthread.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <condition_variable>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <sstream>
#include <thread>

namespace {

using namespace slicestation;
using namespace slicestation::daemon;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

AlertRecord sampleAlert(std::int64_t id = 12, AlertKind kind = AlertKind::Damaged,
                        AlertSeverity severity = AlertSeverity::Warning) {
    AlertRecord a;
    a.id = id;
    a.kind = kind;
    a.severity = severity;
    a.message = "section s01-3 is torn (\"tear\" 4.2% of the area)";
    a.runId = 3;
    a.sectionId = 17;
    a.raisedUtc = "2024-05-01T22:15:03.123Z";
    return a;
}

/// A webhook receiver on 127.0.0.1 at a free port. `status(n)` answers the n-th request (from 0);
/// with hang(), every request blocks until the receiver is destroyed.
class Receiver {
public:
    struct Hit {
        Clock::time_point at;
        std::string path, body, contentType;
    };

    explicit Receiver(std::function<int(int)> status = [](int) { return 200; })
        : status_(std::move(status)) {
        server_.Post(".*", [this](const httplib::Request& req, httplib::Response& res) {
            int n = 0;
            {
                std::unique_lock lock(mutex_);
                n = static_cast<int>(hits_.size());
                hits_.push_back(
                    {Clock::now(), req.path, req.body, req.get_header_value("Content-Type")});
                cv_.notify_all();
                if (hang_)
                    cv_.wait_for(lock, 10s, [this] { return released_; });
            }
            res.status = status_(n);
            res.set_content("answer " + std::to_string(res.status), "text/plain");
        });
        port_ = server_.bind_to_any_port("127.0.0.1");
        thread_ = std::thread([this] { server_.listen_after_bind(); });
    }
    ~Receiver() {
        {
            std::lock_guard lock(mutex_);
            released_ = true;
            cv_.notify_all();
        }
        server_.stop();
        thread_.join();
    }
    void hang() {
        std::lock_guard lock(mutex_);
        hang_ = true;
    }
    int port() const { return port_; }
    std::string url(const std::string& path = "/hook") const {
        return "http://127.0.0.1:" + std::to_string(port_) + path;
    }
    bool waitHits(std::size_t n, std::chrono::milliseconds timeout) {
        std::unique_lock lock(mutex_);
        return cv_.wait_for(lock, timeout, [&] { return hits_.size() >= n; });
    }
    std::vector<Hit> hits() {
        std::lock_guard lock(mutex_);
        return hits_;
    }

private:
    std::function<int(int)> status_;
    httplib::Server server_;
    int port_ = 0;
    std::thread thread_;
    std::mutex mutex_;
    std::condition_variable cv_;
    std::vector<Hit> hits_;
    bool hang_ = false, released_ = false;
};

/// A port on 127.0.0.1 that refuses connections: bound, never listening, held until destroyed.
class RefusingPort {
public:
    RefusingPort() : fd_(socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0)) {
        sockaddr_in a{};
        a.sin_family = AF_INET;
        a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        EXPECT_EQ(bind(fd_.get(), reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
        socklen_t len = sizeof a;
        EXPECT_EQ(getsockname(fd_.get(), reinterpret_cast<sockaddr*>(&a), &len), 0);
        port_ = ntohs(a.sin_port);
    }
    std::string url() const { return "http://127.0.0.1:" + std::to_string(port_) + "/hook"; }

private:
    core::UniqueFd fd_;
    int port_ = 0;
};

/// Records what it is given; can be told to block in deliver() until released.
struct Recorded {
    std::mutex mutex;
    std::condition_variable cv;
    std::vector<std::pair<Clock::time_point, AlertRecord>> got;
    bool block = false;
    bool waiting = false; ///< a deliver() is blocked
};

class RecordingSink final : public AlertChannelSink {
public:
    explicit RecordingSink(std::shared_ptr<Recorded> r) : r_(std::move(r)) {}
    std::string name() const override { return "recording"; }
    core::Result<void> deliver(const AlertRecord& alert) override {
        std::unique_lock lock(r_->mutex);
        r_->waiting = true;
        r_->cv.notify_all();
        r_->cv.wait_for(lock, 10s, [this] { return !r_->block; });
        r_->waiting = false;
        r_->got.emplace_back(Clock::now(), alert);
        r_->cv.notify_all();
        return {};
    }

private:
    std::shared_ptr<Recorded> r_;
};

AlertSettings fastPolicy(int retries = 2, std::chrono::milliseconds backoff = 10ms) {
    AlertSettings s;
    s.journal = false;
    s.retries = retries;
    s.backoffInitial = backoff;
    s.backoffMax = backoff * 100;
    s.maxPerWindow = 0;
    return s;
}

std::unique_ptr<AlertChannelSink>
webhook(const std::string& url, WebhookSettings::Format format = WebhookSettings::Format::Json,
        std::chrono::milliseconds timeout = 2s) {
    auto sink = WebhookSink::create({url, format, timeout});
    EXPECT_TRUE(sink) << sink.error().message;
    return sink ? std::move(*sink) : nullptr;
}

std::unique_ptr<AlertChannelSink> command(std::string script,
                                          std::chrono::milliseconds timeout = 5s) {
    auto sink = CommandSink::create({{"/bin/sh", "-c", std::move(script)}, timeout});
    EXPECT_TRUE(sink) << sink.error().message;
    return sink ? std::move(*sink) : nullptr;
}

std::vector<std::unique_ptr<AlertChannelSink>>
sinks(std::unique_ptr<AlertChannelSink> a, std::unique_ptr<AlertChannelSink> b = nullptr,
      std::unique_ptr<AlertChannelSink> c = nullptr) {
    std::vector<std::unique_ptr<AlertChannelSink>> v;
    for (auto* s : {&a, &b, &c})
        if (*s)
            v.push_back(std::move(*s));
    return v;
}

fs::path tempDir(const std::string& name) {
    fs::path d =
        fs::path(testing::TempDir()) / ("slst-alerts-" + std::to_string(getpid()) + "-" + name);
    fs::remove_all(d);
    fs::create_directories(d);
    return d;
}

std::string readText(const fs::path& p) {
    std::ifstream in(p);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

std::string hostName() {
    char buf[256] = {};
    gethostname(buf, sizeof buf - 1);
    return buf;
}

// Settings -------------------------------------------------------------------------------------

core::Result<AlertSettings> parseToml(const std::string& toml) {
    auto doc = parseDocument(toml, DocumentFormat::Toml, "station.toml");
    EXPECT_TRUE(doc) << doc.error().message;
    if (!doc)
        return doc.error();
    return parseAlertSettings(*doc, "station.toml");
}

TEST(AlertSettings, ParsesAFullTable) {
    auto s = parseToml(R"(
[alerts]
journal = false
retries = 2
backoff_initial_ms = 250
backoff_max_ms = 4000
max_per_minute = 5
min_severity = "warning"
[[alerts.webhook]]
url = "http://127.0.0.1:9000/hook?x=1"
format = "slack"
timeout_s = 2.5
[[alerts.webhook]]
url = "https://hooks.example.org/services/T0/B0/secret"
[[alerts.command]]
argv = ["/usr/local/bin/notify-tech", "--urgent"]
timeout_s = 10
)");
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_FALSE(s->journal);
    EXPECT_EQ(s->retries, 2);
    EXPECT_EQ(s->backoffInitial, 250ms);
    EXPECT_EQ(s->backoffMax, 4000ms);
    EXPECT_EQ(s->maxPerWindow, 5);
    EXPECT_EQ(s->rateWindow, 60s);
    EXPECT_EQ(s->minSeverity, AlertSeverity::Warning);
    ASSERT_EQ(s->webhooks.size(), 2u);
    EXPECT_EQ(s->webhooks[0].url, "http://127.0.0.1:9000/hook?x=1");
    EXPECT_EQ(s->webhooks[0].format, WebhookSettings::Format::Slack);
    EXPECT_EQ(s->webhooks[0].timeout, 2500ms);
    EXPECT_EQ(s->webhooks[1].format, WebhookSettings::Format::Json);
    EXPECT_EQ(s->webhooks[1].timeout, 5s);
    ASSERT_EQ(s->commands.size(), 1u);
    EXPECT_EQ(s->commands[0].argv,
              (std::vector<std::string>{"/usr/local/bin/notify-tech", "--urgent"}));
    EXPECT_EQ(s->commands[0].timeout, 10s);

    auto made = makeAlertSinks(*s);
    ASSERT_TRUE(made) << made.error().message;
    ASSERT_EQ(made->size(), 3u);
    EXPECT_EQ((*made)[0]->name(), "webhook http://127.0.0.1:9000/...");
    EXPECT_EQ((*made)[1]->name(), "webhook https://hooks.example.org:443/...")
        << "the secret path is not shown";
    EXPECT_EQ((*made)[2]->name(), "command /usr/local/bin/notify-tech --urgent");
}

TEST(AlertSettings, AbsentTableMeansJournalOnly) {
    auto s =
        parseAlertSettings(nlohmann::json{{"daemon", nlohmann::json::object()}}, "station.toml");
    ASSERT_TRUE(s) << s.error().message;
    EXPECT_TRUE(s->journal);
    EXPECT_EQ(s->retries, 4);
    EXPECT_EQ(s->backoffInitial, 1000ms);
    EXPECT_EQ(s->backoffMax, 60000ms);
    EXPECT_EQ(s->maxPerWindow, 20);
    EXPECT_EQ(s->minSeverity, AlertSeverity::Info);
    auto made = makeAlertSinks(*s);
    ASSERT_TRUE(made);
    ASSERT_EQ(made->size(), 1u);
    EXPECT_EQ((*made)[0]->name(), "journal");
}

TEST(AlertSettings, ErrorsNameTheKey) {
    const auto expectError = [](const std::string& toml, const std::string& prefix) {
        auto s = parseToml(toml);
        ASSERT_FALSE(s) << toml;
        EXPECT_EQ(s.error().code, core::ErrorCode::InvalidArgument);
        EXPECT_EQ(s.error().message.rfind(prefix, 0), 0u) << s.error().message;
    };
    expectError("[alerts]\n[[alerts.webhook]]\nurl = \"ftp://host/x\"\n",
                "station.toml: alerts.webhook[0].url: ");
    expectError("[alerts]\n[[alerts.webhook]]\nurl = \"http://ok/\"\n[[alerts.webhook]]\nurl = "
                "\"http://:80/x\"\n",
                "station.toml: alerts.webhook[1].url: ");
    expectError("[alerts]\n[[alerts.webhook]]\nurl = \"http://host:99999/\"\n",
                "station.toml: alerts.webhook[0].url: ");
    expectError("[alerts]\n[[alerts.webhook]]\nurl = \"http://h/\"\nformat = \"teams\"\n",
                "station.toml: alerts.webhook[0].format: ");
    expectError("[alerts]\n[[alerts.webhook]]\nformat = \"json\"\n",
                "station.toml: alerts.webhook[0].url: missing");
    expectError("[alerts]\n[[alerts.webhook]]\nurl = \"http://h/\"\nurl_typo = 1\n",
                "station.toml: alerts.webhook[0]: unknown key \"url_typo\" (known: url, format, "
                "timeout_s)");
    expectError("[alerts]\n[[alerts.command]]\nargv = []\n",
                "station.toml: alerts.command[0].argv: empty");
    expectError("[alerts]\n[[alerts.command]]\nargv = [\"\"]\n",
                "station.toml: alerts.command[0].argv: ");
    expectError("[alerts]\n[[alerts.command]]\nargv = [\"x\", 3]\n",
                "station.toml: alerts.command[0].argv: ");
    expectError("[alerts]\nretry = 3\n",
                "station.toml: alerts: unknown key \"retry\"; did you mean \"retries\"?");
    expectError("[alerts]\nmin_severity = \"urgent\"\n", "station.toml: alerts.min_severity: ");
    expectError("[alerts]\nretries = -1\n", "station.toml: alerts.retries: ");
    expectError("[alerts]\nbackoff_initial_ms = 5000\nbackoff_max_ms = 100\n",
                "station.toml: alerts.backoff_max_ms: ");
    expectError("[alerts.webhook]\nurl = \"http://h/\"\n",
                "station.toml: alerts.webhook: expected [[alerts.webhook]]");
    expectError("alerts = 3\n", "station.toml: alerts: expected a table");
}

// Webhook --------------------------------------------------------------------------------------

TEST(WebhookChannel, JsonBodyCarriesTheAlert) {
    Receiver rx;
    AlertDispatcher d(fastPolicy(), sinks(webhook(rx.url())));
    const AlertRecord a = sampleAlert();
    d.post(a);
    ASSERT_TRUE(rx.waitHits(1, 5s));
    ASSERT_TRUE(d.waitIdle(5s));
    const auto hit = rx.hits().at(0);
    EXPECT_EQ(hit.path, "/hook");
    EXPECT_EQ(hit.contentType, "application/json");
    const auto j = nlohmann::json::parse(hit.body);
    EXPECT_EQ(j.at("id"), a.id);
    EXPECT_EQ(j.at("kind"), "damaged");
    EXPECT_EQ(j.at("severity"), "warning");
    EXPECT_EQ(j.at("message"), a.message);
    EXPECT_EQ(j.at("run_id"), *a.runId);
    EXPECT_EQ(j.at("section_id"), *a.sectionId);
    EXPECT_EQ(j.at("raised_utc"), a.raisedUtc);
    EXPECT_EQ(j.at("open"), true);
    EXPECT_EQ(j.at("station"), hostName());
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.delivered, 1u);
    EXPECT_EQ(st.failed, 0u);
    EXPECT_EQ(st.retried, 0u);
}

TEST(WebhookChannel, SlackBodyIsText) {
    Receiver rx;
    AlertDispatcher d(fastPolicy(),
                      sinks(webhook(rx.url("/services/T/B/x"), WebhookSettings::Format::Slack)));
    d.post(sampleAlert());
    ASSERT_TRUE(rx.waitHits(1, 5s));
    const auto hit = rx.hits().at(0);
    EXPECT_EQ(hit.path, "/services/T/B/x");
    const auto j = nlohmann::json::parse(hit.body);
    ASSERT_EQ(j.size(), 1u) << hit.body;
    EXPECT_EQ(j.at("text"), "[warning] damaged: " + sampleAlert().message + " (run 3, section 17)");
}

TEST(WebhookChannel, RetriesWithDoublingBackoff) {
    Receiver rx([](int n) { return n < 2 ? 500 : 200; });
    AlertDispatcher d(fastPolicy(4, 40ms), sinks(webhook(rx.url())));
    d.post(sampleAlert());
    ASSERT_TRUE(rx.waitHits(3, 5s));
    ASSERT_TRUE(d.waitIdle(5s));
    const auto hits = rx.hits();
    ASSERT_EQ(hits.size(), 3u) << "delivered on the third attempt, then no more";
    const auto gap1 = hits[1].at - hits[0].at, gap2 = hits[2].at - hits[1].at;
    EXPECT_GE(gap1, 40ms);
    EXPECT_GE(gap2, 80ms) << "the backoff doubles";
    EXPECT_LT(gap2, 2s);
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.delivered, 1u);
    EXPECT_EQ(st.retried, 2u);
    EXPECT_EQ(st.failed, 0u);
    EXPECT_NE(st.lastError.find("HTTP status 500"), std::string::npos) << st.lastError;
}

TEST(WebhookChannel, GivesUpWithoutBlockingOtherChannels) {
    Receiver failing([](int) { return 503; });
    RefusingPort refusing;
    Receiver good;
    std::vector<std::tuple<std::string, AlertRecord, core::Error>> givenUp;
    std::mutex givenUpMutex;
    AlertDispatcher d(fastPolicy(2, 5ms),
                      sinks(webhook(failing.url()), webhook(refusing.url()), webhook(good.url())),
                      [&](const std::string& channel, const AlertRecord& a, const core::Error& e) {
                          std::lock_guard lock(givenUpMutex);
                          givenUp.emplace_back(channel, a, e);
                      });
    d.post(sampleAlert(1));
    d.post(sampleAlert(2));
    ASSERT_TRUE(good.waitHits(2, 5s));
    ASSERT_TRUE(d.waitIdle(5s));
    EXPECT_EQ(failing.hits().size(), 6u) << "retries + 1 attempts for each of two alerts";
    const auto st = d.stats();
    EXPECT_EQ(st[0].failed, 2u);
    EXPECT_EQ(st[0].retried, 4u);
    EXPECT_EQ(st[0].delivered, 0u);
    EXPECT_NE(st[0].lastError.find("HTTP status 503"), std::string::npos) << st[0].lastError;
    EXPECT_NE(st[0].lastError.find("127.0.0.1:" + std::to_string(failing.port())),
              std::string::npos)
        << st[0].lastError;
    EXPECT_EQ(st[1].failed, 2u);
    EXPECT_EQ(st[1].delivered, 0u);
    EXPECT_NE(st[1].lastError.find("no response"), std::string::npos) << st[1].lastError;
    EXPECT_EQ(st[2].delivered, 2u);
    EXPECT_EQ(st[2].failed, 0u);
    std::lock_guard lock(givenUpMutex);
    EXPECT_EQ(givenUp.size(), 4u);
}

TEST(WebhookChannel, SlowReceiverTimesOutAndDoesNotDelayOthers) {
    Receiver slow;
    slow.hang();
    Receiver good;
    AlertDispatcher d(
        fastPolicy(0),
        sinks(webhook(slow.url(), WebhookSettings::Format::Json, 800ms), webhook(good.url())));
    const auto t0 = Clock::now();
    d.post(sampleAlert());
    ASSERT_TRUE(slow.waitHits(1, 5s));
    ASSERT_TRUE(good.waitHits(1, 5s));
    {
        const auto st = d.stats();
        EXPECT_EQ(st[0].delivered + st[0].failed, 0u)
            << "the good channel got it while the slow one still waits";
    }
    ASSERT_TRUE(d.waitIdle(5s));
    EXPECT_GE(Clock::now() - t0, 800ms);
    const auto st = d.stats();
    EXPECT_EQ(st[0].failed, 1u);
    EXPECT_NE(st[0].lastError.find("no response"), std::string::npos) << st[0].lastError;
    EXPECT_EQ(st[1].delivered, 1u);
}

TEST(WebhookChannel, CreateRefusesBadUrls) {
    for (const char* url :
         {"ftp://h/x", "http://", "http://h:0/", "http://user:pw@h/", "http://h x/"}) {
        auto s = WebhookSink::create({url, WebhookSettings::Format::Json, 1s});
        ASSERT_FALSE(s) << url;
        EXPECT_EQ(s.error().code, core::ErrorCode::InvalidArgument) << url;
    }
}

TEST(WebhookChannel, ErrorCodes) {
    RefusingPort refusing;
    Receiver failing([](int) { return 404; });
    Receiver slow;
    slow.hang();
    const auto code = [](const std::string& url, std::chrono::milliseconds timeout) {
        auto sink = WebhookSink::create({url, WebhookSettings::Format::Json, timeout});
        EXPECT_TRUE(sink);
        auto r = (*sink)->deliver(sampleAlert());
        EXPECT_FALSE(r);
        return r ? core::ErrorCode::Internal : r.error().code;
    };
    EXPECT_EQ(code(refusing.url(), 1s), core::ErrorCode::Disconnected);
    EXPECT_EQ(code(failing.url(), 1s), core::ErrorCode::IoError);
    EXPECT_EQ(code(slow.url(), 200ms), core::ErrorCode::Timeout);
}

// Command --------------------------------------------------------------------------------------

TEST(CommandChannel, CreateRefusesAnEmptyArgv) {
    for (const auto& argv : {std::vector<std::string>{}, std::vector<std::string>{""}}) {
        auto s = CommandSink::create({argv, 1s});
        ASSERT_FALSE(s);
        EXPECT_EQ(s.error().code, core::ErrorCode::InvalidArgument);
    }
}

TEST(CommandChannel, GetsTheAlertInItsEnvironment) {
    const fs::path dir = tempDir("env");
    const fs::path out = dir / "env.txt";
    // A stale value in the daemon's environment must not win over the alert's.
    setenv("SLST_ALERT_KIND", "stale", 1);
    // The daemon blocks SIGTERM in every thread and ignores SIGPIPE; the command must inherit
    // neither. `cp` shows its own mask (a shell would reset it at start).
    sigset_t term, old;
    sigemptyset(&term);
    sigaddset(&term, SIGTERM);
    pthread_sigmask(SIG_BLOCK, &term, &old);
    const auto oldPipe = std::signal(SIGPIPE, SIG_IGN);
    {
        auto status =
            CommandSink::create({{"/bin/cp", "/proc/self/status", out.string() + ".status"}, 5s});
        ASSERT_TRUE(status);
        AlertDispatcher d(fastPolicy(0),
                          sinks(command("env > '" + out.string() + "'; readlink /proc/$$/fd/0 > '" +
                                        out.string() + ".stdin'"),
                                std::move(*status)));
        pthread_sigmask(SIG_SETMASK, &old, nullptr);
        std::signal(SIGPIPE, oldPipe);
        AlertRecord a = sampleAlert();
        a.sectionId.reset();
        d.post(a);
        ASSERT_TRUE(d.waitIdle(5s));
        for (const auto& st : d.stats())
            EXPECT_EQ(st.delivered, 1u) << st.name << ": " << st.lastError;
    }
    unsetenv("SLST_ALERT_KIND");
    std::map<std::string, std::vector<std::string>> env;
    std::istringstream lines(readText(out));
    for (std::string line; std::getline(lines, line);) {
        const auto eq = line.find('=');
        if (eq != std::string::npos)
            env[line.substr(0, eq)].push_back(line.substr(eq + 1));
    }
    const AlertRecord a = sampleAlert();
    const auto one = [&](const std::string& key) {
        EXPECT_EQ(env[key].size(), 1u) << key;
        return env[key].empty() ? std::string("<absent>") : env[key][0];
    };
    EXPECT_EQ(one("SLST_ALERT_ID"), "12");
    EXPECT_EQ(one("SLST_ALERT_KIND"), "damaged");
    EXPECT_EQ(one("SLST_ALERT_SEVERITY"), "warning");
    EXPECT_EQ(one("SLST_ALERT_MESSAGE"), a.message);
    EXPECT_EQ(one("SLST_ALERT_RUN_ID"), "3");
    EXPECT_EQ(one("SLST_ALERT_SECTION_ID"), "");
    EXPECT_EQ(one("SLST_ALERT_RAISED_UTC"), a.raisedUtc);
    const auto j = nlohmann::json::parse(one("SLST_ALERT_JSON"));
    EXPECT_EQ(j.at("id"), 12);
    EXPECT_EQ(j.at("message"), a.message);
    EXPECT_TRUE(j.at("section_id").is_null());
    EXPECT_EQ(env["PATH"].size(), 1u) << "the daemon's environment is passed on";
    EXPECT_EQ(readText(out.string() + ".stdin"), "/dev/null\n");
    const std::string status = readText(out.string() + ".status");
    EXPECT_NE(status.find("\nSigBlk:\t0000000000000000\n"), std::string::npos) << status;
    const auto ign = status.find("\nSigIgn:\t");
    ASSERT_NE(ign, std::string::npos);
    const auto ignored = std::stoull(status.substr(ign + 9, 16), nullptr, 16);
    EXPECT_EQ(ignored & (1ull << (SIGPIPE - 1)), 0u) << "SIGPIPE back to its default";
    fs::remove_all(dir);
}

TEST(CommandChannel, FailingCommandIsRetriedThenGivenUp) {
    const fs::path dir = tempDir("fail");
    const fs::path count = dir / "attempts";
    AlertDispatcher d(fastPolicy(2, 5ms),
                      sinks(command("echo x >> '" + count.string() + "'; exit 3")));
    d.post(sampleAlert());
    ASSERT_TRUE(d.waitIdle(5s));
    EXPECT_EQ(readText(count), "x\nx\nx\n");
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.failed, 1u);
    EXPECT_EQ(st.retried, 2u);
    EXPECT_EQ(st.delivered, 0u);
    EXPECT_NE(st.lastError.find("command /bin/sh -c"), std::string::npos) << st.lastError;
    EXPECT_NE(st.lastError.find("exited with status 3"), std::string::npos) << st.lastError;
    fs::remove_all(dir);
}

TEST(CommandChannel, SignalledCommandFails) {
    auto sink = CommandSink::create({{"/bin/sh", "-c", "kill -KILL $$"}, 5s});
    ASSERT_TRUE(sink);
    auto r = (*sink)->deliver(sampleAlert());
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("killed by signal 9"), std::string::npos) << r.error().message;
}

TEST(CommandChannel, MissingProgramIsNotFound) {
    auto sink = CommandSink::create({{"/nonexistent/slst-notify"}, 5s});
    ASSERT_TRUE(sink);
    auto r = (*sink)->deliver(sampleAlert());
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, core::ErrorCode::NotFound);
    EXPECT_NE(r.error().message.find("/nonexistent/slst-notify"), std::string::npos)
        << r.error().message;
}

bool processGone(pid_t pid) {
    std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
    std::string text;
    if (!std::getline(stat, text))
        return true;
    const auto close = text.rfind(')');
    return close != std::string::npos && close + 2 < text.size() && text[close + 2] == 'Z';
}

TEST(CommandChannel, HangingCommandIsKilledAtItsTimeout) {
    const fs::path dir = tempDir("hang");
    const fs::path pids = dir / "pids";
    auto sink = CommandSink::create(
        {{"/bin/sh", "-c", "sleep 30 & echo $$ $! > '" + pids.string() + "'; wait"}, 300ms});
    ASSERT_TRUE(sink);
    const auto t0 = Clock::now();
    auto r = (*sink)->deliver(sampleAlert());
    const auto took = Clock::now() - t0;
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, core::ErrorCode::Timeout);
    EXPECT_NE(r.error().message.find("did not finish within 0.3 s: killed"), std::string::npos)
        << r.error().message;
    EXPECT_GE(took, 300ms);
    EXPECT_LT(took, 5s);
    pid_t shell = 0, sleeper = 0;
    std::istringstream(readText(pids)) >> shell >> sleeper;
    ASSERT_GT(shell, 0);
    ASSERT_GT(sleeper, 0);
    EXPECT_TRUE(processGone(shell)) << "the child is reaped";
    // The grandchild belongs to the killed process group; its new parent reaps it.
    const auto until = Clock::now() + 5s;
    while (!processGone(sleeper) && Clock::now() < until)
        std::this_thread::sleep_for(10ms);
    EXPECT_TRUE(processGone(sleeper)) << "the whole process group is killed";
    fs::remove_all(dir);
}

// Rate limit, queue, severity ------------------------------------------------------------------

TEST(AlertDispatcher, RateLimitHoldsAndSummarises) {
    auto rec = std::make_shared<Recorded>();
    AlertSettings p = fastPolicy();
    p.maxPerWindow = 3;
    p.rateWindow = 300ms;
    AlertDispatcher d(p, sinks(std::make_unique<RecordingSink>(rec)));
    for (int i = 1; i <= 10; ++i)
        d.post(sampleAlert(i, i <= 8 ? AlertKind::Damaged : AlertKind::LowDisk,
                           i == 10 ? AlertSeverity::Critical : AlertSeverity::Warning));
    ASSERT_TRUE(d.waitIdle(5s));
    std::lock_guard lock(rec->mutex);
    ASSERT_EQ(rec->got.size(), 4u);
    for (int i = 0; i < 3; ++i)
        EXPECT_EQ(rec->got[static_cast<std::size_t>(i)].second.id, i + 1);
    const auto& [at, summary] = rec->got[3];
    EXPECT_EQ(summary.kind, AlertKind::AlertSummary);
    EXPECT_EQ(summary.severity, AlertSeverity::Critical) << "the highest held severity";
    EXPECT_EQ(summary.message.rfind("7 more alerts: kinds damaged (x5), low_disk (x2)", 0), 0u)
        << summary.message;
    EXPECT_GE(at - rec->got[0].first, 250ms) << "sent once the window had room";
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.delivered, 4u);
    EXPECT_EQ(st.suppressed, 7u);
    EXPECT_EQ(st.summaries, 1u);
}

TEST(AlertDispatcher, FullQueueDropsTheOldest) {
    auto rec = std::make_shared<Recorded>();
    rec->block = true;
    AlertSettings p = fastPolicy();
    p.queueCapacity = 3;
    AlertDispatcher d(p, sinks(std::make_unique<RecordingSink>(rec)));
    d.post(sampleAlert(1));
    {
        std::unique_lock lock(rec->mutex);
        ASSERT_TRUE(rec->cv.wait_for(lock, 5s, [&] { return rec->waiting; }));
    }
    for (int i = 2; i <= 6; ++i)
        d.post(sampleAlert(i));
    {
        std::lock_guard lock(rec->mutex);
        rec->block = false;
        rec->cv.notify_all();
    }
    ASSERT_TRUE(d.waitIdle(5s));
    std::lock_guard lock(rec->mutex);
    std::vector<std::int64_t> ids;
    for (const auto& g : rec->got)
        ids.push_back(g.second.id);
    EXPECT_EQ(ids, (std::vector<std::int64_t>{1, 4, 5, 6}));
    EXPECT_EQ(d.stats().at(0).dropped, 2u);
}

TEST(AlertDispatcher, BelowMinSeverityIsNotSent) {
    auto rec = std::make_shared<Recorded>();
    AlertSettings p = fastPolicy();
    p.minSeverity = AlertSeverity::Warning;
    AlertDispatcher d(p, sinks(std::make_unique<RecordingSink>(rec)));
    d.post(sampleAlert(1, AlertKind::RunFinished, AlertSeverity::Info));
    d.post(sampleAlert(2, AlertKind::Damaged, AlertSeverity::Warning));
    d.post(sampleAlert(3, AlertKind::RunFailed, AlertSeverity::Critical));
    ASSERT_TRUE(d.waitIdle(5s));
    std::lock_guard lock(rec->mutex);
    ASSERT_EQ(rec->got.size(), 2u);
    EXPECT_EQ(rec->got[0].second.id, 2);
    EXPECT_EQ(rec->got[1].second.id, 3);
}

// Journal --------------------------------------------------------------------------------------

TEST(JournalChannel, SendsTheExactFields) {
    std::mutex mutex;
    std::vector<std::vector<std::string>> sent;
    AlertSettings p = fastPolicy(0);
    p.journal = true;
    auto made = makeAlertSinks(p, [&](const std::vector<std::string>& fields) {
        std::lock_guard lock(mutex);
        sent.push_back(fields);
        return 0;
    });
    ASSERT_TRUE(made);
    AlertDispatcher d(p, std::move(*made));
    d.post(sampleAlert(12, AlertKind::Damaged, AlertSeverity::Warning));
    AlertRecord bare = sampleAlert(13, AlertKind::RunFailed, AlertSeverity::Critical);
    bare.runId.reset();
    bare.sectionId.reset();
    bare.message = "run failed";
    d.post(bare);
    d.post(sampleAlert(14, AlertKind::RunFinished, AlertSeverity::Info));
    ASSERT_TRUE(d.waitIdle(5s));
    std::lock_guard lock(mutex);
    ASSERT_EQ(sent.size(), 3u);
    EXPECT_EQ(sent[0], (std::vector<std::string>{"MESSAGE=ALERT damaged: " + sampleAlert().message,
                                                 "PRIORITY=4", "SYSLOG_IDENTIFIER=slicestationd",
                                                 "SLST_ALERT_ID=12", "SLST_ALERT_KIND=damaged",
                                                 "SLST_ALERT_SEVERITY=warning", "SLST_RUN_ID=3",
                                                 "SLST_SECTION_ID=17"}));
    EXPECT_EQ(sent[1], (std::vector<std::string>{"MESSAGE=ALERT run_failed: run failed",
                                                 "PRIORITY=2", "SYSLOG_IDENTIFIER=slicestationd",
                                                 "SLST_ALERT_ID=13", "SLST_ALERT_KIND=run_failed",
                                                 "SLST_ALERT_SEVERITY=critical"}));
    EXPECT_EQ(sent[2].at(1), "PRIORITY=5");
    EXPECT_EQ(d.stats().at(0).delivered, 3u);
}

TEST(JournalChannel, MissingJournaldIsCountedNotRetried) {
    std::atomic<int> calls{0};
    AlertDispatcher d(fastPolicy(3, 5ms),
                      sinks(std::make_unique<JournalSink>([&](const std::vector<std::string>&) {
                          ++calls;
                          return -ENOENT;
                      })));
    d.post(sampleAlert());
    ASSERT_TRUE(d.waitIdle(5s));
    EXPECT_EQ(calls, 1);
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.failed, 1u);
    EXPECT_EQ(st.retried, 0u);
    EXPECT_NE(st.lastError.find("sd_journal_sendv"), std::string::npos) << st.lastError;
}

// stop() ---------------------------------------------------------------------------------------

TEST(AlertDispatcher, StopEndsLongBackoffWithinTheDeadline) {
    RefusingPort down;
    AlertDispatcher d(fastPolicy(4, 30s), sinks(webhook(down.url())));
    d.post(sampleAlert(1));
    d.post(sampleAlert(2));
    const auto t0 = Clock::now();
    d.stop(300ms);
    const auto took = Clock::now() - t0;
    EXPECT_LT(took, 2s) << "backoff waits end at the stop deadline";
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.delivered, 0u);
    EXPECT_EQ(st.failed, 1u);
    EXPECT_EQ(st.dropped, 1u) << "the second alert was never attempted";
    d.post(sampleAlert(3)); // ignored after stop
    d.stop(300ms);          // idempotent
    EXPECT_EQ(d.stats().at(0).dropped, 1u);
}

TEST(AlertDispatcher, StopDrainsWhatItCan) {
    Receiver rx;
    AlertDispatcher d(fastPolicy(), sinks(webhook(rx.url())));
    for (int i = 1; i <= 5; ++i)
        d.post(sampleAlert(i));
    d.stop(5s);
    EXPECT_EQ(rx.hits().size(), 5u);
    EXPECT_EQ(d.stats().at(0).delivered, 5u);
}

TEST(AlertDispatcher, StopCancelsAHungCommand) {
    AlertDispatcher d(fastPolicy(0), sinks(command("sleep 30", 30s)));
    d.post(sampleAlert());
    const auto t0 = Clock::now();
    // Give the worker a moment to start the command; stop must then cut it short.
    ASSERT_FALSE(d.waitIdle(200ms));
    d.stop(100ms);
    EXPECT_LT(Clock::now() - t0, 3s);
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.failed, 1u);
    EXPECT_NE(st.lastError.find("stopped"), std::string::npos) << st.lastError;
}

TEST(AlertDispatcher, StopCancelsASlowWebhook) {
    Receiver slow;
    slow.hang();
    AlertDispatcher d(fastPolicy(0),
                      sinks(webhook(slow.url(), WebhookSettings::Format::Json, 30s)));
    d.post(sampleAlert());
    ASSERT_TRUE(slow.waitHits(1, 5s));
    const auto t0 = Clock::now();
    d.stop(100ms);
    EXPECT_LT(Clock::now() - t0, 3s) << "the request in flight is cut at the deadline";
    const auto st = d.stats().at(0);
    EXPECT_EQ(st.failed, 1u);
    EXPECT_NE(st.lastError.find("stopped"), std::string::npos) << st.lastError;
}

} // namespace
