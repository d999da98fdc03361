// slicestationd as a process, as systemd runs it: the real binary, the real Modbus stage driver
// talking to a stage-sim server (in this process, TCP on loopback), the simulated camera over a
// virtual slide of generated sections, the built-in atlas.
// - killed with SIGKILL at random moments and restarted, over and over: no section lost, none
//   captured twice, no half-written file referenced, the journal passes integrity_check;
// - sd_notify against a fake NOTIFY_SOCKET: READY, STATUS, WATCHDOG while working, none while
//   a move hangs, STOPPING and a clean exit on SIGTERM;
// - stage faults injected in the Modbus server during runs: an alarm pauses the run until the
//   technician asks for the alarm reset; dropped, corrupt, busy and slow replies are retried.
#include "../../common/test_dir.hpp"
#include "../../common/time_scale.hpp"
#include "fake_notify_socket.hpp"
#include "slicestation/core/atomic_file.hpp"
#include "slicestation/daemon/storage/journal.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"
#include "slicestation/sim/modbus_stage_server.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <nlohmann/json.hpp>

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

extern char** environ;

namespace slicestation::test {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

/// Deadlines are for a loaded machine; SLST_TEST_TIME_SCALE (the sanitizer build sets it, the
/// daemon runs several times slower there) stretches every one of them, and the kill moments.
using testing_time::timeScale;
template <class Rep, class Period>
std::chrono::milliseconds scaled(std::chrono::duration<Rep, Period> d) {
    return std::chrono::milliseconds(static_cast<std::int64_t>(
        std::chrono::duration<double, std::milli>(d).count() * timeScale()));
}

constexpr const char* kToken = "process-test-token-0123";
constexpr int kSections = 6; // two slides of three
const double kAp[kSections] = {0.30, 0.38, 0.46, 0.54, 0.62, 0.70};
constexpr int kTorn = 1; // the second section is torn

double centreX(int i) {
    return 5'000 + 1'000 + (i % 3 + 0.5) * 14'000;
}
double centreY(int i) {
    return 5'000 + 1'000 + (i / 3 + 0.5) * 14'000;
}

std::string stationToml(int stagePort, const std::string& scanExtra, const std::string& daemonExtra,
                        int moveTimeoutS) {
    std::ostringstream t;
    t << "[stage]\ndriver = \"modbus\"\ntransport = \"tcp\"\nhost = \"127.0.0.1\"\nport = "
      << stagePort << "\npreset = \"oriental-az\"\nmove_timeout_s = " << moveTimeoutS
      << "\nspeed_um_per_s = 40000\naccel_um_per_s2 = 200000\n"
         "settle_ms = 20\nresponse_timeout_ms = 200\nretries = 2\n"
         "[stage.axes.x]\nslave = 1\nsteps_per_um = 2.0\nmin_um = 0\nmax_um = 75000\n"
         "[stage.axes.y]\nslave = 2\nsteps_per_um = 2.0\nmin_um = 0\nmax_um = 50000\n"
         "[stage.axes.z]\nslave = 3\nsteps_per_um = 10.0\nmin_um = 0\nmax_um = 5000\n"
         "[camera]\ndriver = \"sim\"\nformat = \"mono16\"\nwidth = 640\nheight = 512\n"
         "[camera.sim]\nsensor_um_per_px = 20.0\nfocus_z_um = 2500\nfocus_tilt_x = 0.002\n"
         "slide_origin_x_um = 5000\nslide_origin_y_um = 5000\nslide_um_per_px = 20\ncolumns = 3\n"
         "section_pitch_um = 14000\nsection_width_um = 13000\nmargin_um = 1000\n";
    for (int i = 0; i < kSections; ++i)
        t << "[[camera.sim.sections]]\nap_fraction = " << kAp[i] << "\nseed = " << 40 + i
          << (i == kTorn ? "\ndamage = \"tear\"\n" : "\n");
    t << "[daemon]\natlas = \"builtin\"\nhttp_port = 0\ntoken = \"" << kToken << "\"\n"
      << daemonExtra
      << "[scan]\nobjective = \"sim\"\nwidth = 640\nheight = 512\nstart_z_um = 2500\nmin_free_mb = "
         "50\n"
         "atlas_mismatch_tolerance = 80\nmove_timeout_s = "
      << moveTimeoutS << "\n"
      << scanExtra << "[scan.objectives.sim]\num_per_px = 20.0\n";
    return t.str();
}

std::string planToml() {
    std::ostringstream t;
    t << "name = \"process-test\"\n";
    for (int i = 0; i < kSections; ++i) {
        if (i % 3 == 0)
            t << "[[slides]]\nname = \"slide-0" << i / 3 + 1 << "\"\n";
        t << "[[slides.sections]]\nname = \"s" << i + 1 << "\"\nx_um = " << centreX(i)
          << "\ny_um = " << centreY(i) << "\natlas_slice = " << std::lround(kAp[i] * 80) << "\n";
    }
    return t.str();
}

void writeText(const fs::path& p, const std::string& text) {
    std::ofstream out(p, std::ios::binary);
    out << text;
}

std::string readText(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

/// One slicestationd process; stdout and stderr appended to `log`.
class DaemonProcess {
public:
    DaemonProcess(std::vector<std::string> args, std::vector<std::string> env, fs::path log)
        : args_(std::move(args)), env_(std::move(env)), log_(std::move(log)) {}
    ~DaemonProcess() {
        if (pid_ > 0 && !exited_) {
            ::kill(pid_, SIGKILL);
            int st = 0;
            ::waitpid(pid_, &st, 0);
        }
    }
    bool start() {
        std::vector<std::string> argv{SLICESTATIOND_PATH};
        argv.insert(argv.end(), args_.begin(), args_.end());
        std::vector<char*> av;
        for (auto& a : argv)
            av.push_back(a.data());
        av.push_back(nullptr);
        // The test's environment without systemd's variables, plus what this process gets.
        std::vector<std::string> envs;
        for (char** e = environ; *e; ++e) {
            const std::string v = *e;
            if (v.starts_with("NOTIFY_SOCKET=") || v.starts_with("WATCHDOG_") ||
                v.starts_with("STATE_DIRECTORY="))
                continue;
            envs.push_back(v);
        }
        envs.insert(envs.end(), env_.begin(), env_.end());
        std::vector<char*> ev;
        for (auto& e : envs)
            ev.push_back(e.data());
        ev.push_back(nullptr);
        posix_spawn_file_actions_t fa;
        posix_spawn_file_actions_init(&fa);
        posix_spawn_file_actions_addopen(&fa, 1, log_.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
        posix_spawn_file_actions_adddup2(&fa, 1, 2);
        const int rc = ::posix_spawn(&pid_, av[0], &fa, nullptr, av.data(), ev.data());
        posix_spawn_file_actions_destroy(&fa);
        exited_ = false;
        return rc == 0;
    }
    pid_t pid() const { return pid_; }
    void signal(int sig) { ::kill(pid_, sig); }
    /// True when the process has ended (status in `status`).
    bool poll() {
        if (exited_)
            return true;
        const pid_t r = ::waitpid(pid_, &status_, WNOHANG);
        if (r == pid_)
            exited_ = true;
        return exited_;
    }
    /// Waits for the exit (bounded). \return the exit status, or -1 when still running.
    int waitExit(std::chrono::seconds limit) {
        const auto deadline = Clock::now() + scaled(limit);
        while (!poll()) {
            if (Clock::now() > deadline)
                return -1;
            std::this_thread::sleep_for(20ms); // polling a child's exit
        }
        return WIFEXITED(status_) ? WEXITSTATUS(status_) : 128 + WTERMSIG(status_);
    }
    void killHard() {
        signal(SIGKILL);
        (void)waitExit(30s);
    }

private:
    std::vector<std::string> args_;
    std::vector<std::string> env_;
    fs::path log_;
    pid_t pid_ = -1;
    int status_ = 0;
    bool exited_ = true;
};

/// Every datagram the daemon sends to NOTIFY_SOCKET, with the time it arrived.
class NotifyRecorder {
public:
    NotifyRecorder() {
        thread_ = std::thread([this] {
            while (!stop_) {
                auto m = socket_.receive(100ms);
                if (!m)
                    continue;
                std::lock_guard lock(mutex_);
                messages_.push_back({Clock::now(), *m});
            }
        });
    }
    ~NotifyRecorder() {
        stop_ = true;
        thread_.join();
    }
    const fs::path& path() const { return socket_.path(); }
    bool bound() const { return socket_.bound(); }
    struct Message {
        Clock::time_point at;
        std::string text;
    };
    std::vector<Message> messages() {
        std::lock_guard lock(mutex_);
        return messages_;
    }
    /// Waits (bounded) for a datagram containing `needle` that arrived at or after `since`.
    std::optional<Message> waitFor(const std::string& needle, Clock::time_point since,
                                   std::chrono::seconds limit) {
        const auto deadline = Clock::now() + scaled(limit);
        for (;;) {
            for (const auto& m : messages())
                if (m.at >= since && m.text.find(needle) != std::string::npos)
                    return m;
            if (Clock::now() > deadline)
                return std::nullopt;
            std::this_thread::sleep_for(20ms); // polling the recorder
        }
    }
    int count(const std::string& needle, Clock::time_point from, Clock::time_point to) {
        int n = 0;
        for (const auto& m : messages())
            if (m.at >= from && m.at <= to && m.text.find(needle) != std::string::npos)
                ++n;
        return n;
    }

private:
    FakeNotifySocket socket_;
    std::mutex mutex_;
    std::vector<Message> messages_;
    std::atomic<bool> stop_{false};
    std::thread thread_;
};

class DaemonProcessTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = testing_dir::freshTestDir("daemon");
        sim::StageServerConfig sc;
        sc.slaves = {1, 2, 3};
        auto server = sim::ModbusStageServer::create(sc);
        ASSERT_TRUE(server) << server.error().message;
        server_ = std::move(*server);
        writeText(dir_ / "plan.toml", planToml());
    }
    void TearDown() override {
        daemon_.reset();
        if (server_)
            server_->stop();
        if (HasFailure()) {
            std::cerr << "---- daemon log ----\n"
                      << readText(dir_ / "daemon.log") << "--------------------\n";
            return; // keep the state directory for a look
        }
        fs::remove_all(dir_);
    }

    void writeStation(const std::string& scanExtra = "", const std::string& daemonExtra = "",
                      int moveTimeoutS = 60) {
        writeText(dir_ / "station.toml",
                  stationToml(server_->tcpPort(), scanExtra, daemonExtra, moveTimeoutS));
    }
    fs::path state() const { return dir_ / "state"; }

    /// Starts slicestationd on the station file; `withPlan` submits the plan at start.
    void startDaemon(bool withPlan, std::vector<std::string> env = {}, bool exitWhenIdle = false) {
        std::error_code ec;
        fs::remove(state() / "http.port", ec);
        std::vector<std::string> args{"--config", (dir_ / "station.toml").string(), "--state-dir",
                                      state().string()};
        if (withPlan)
            args.insert(args.end(), {"--plan", (dir_ / "plan.toml").string()});
        if (exitWhenIdle)
            args.push_back("--exit-when-idle");
        daemon_ = std::make_unique<DaemonProcess>(args, std::move(env), dir_ / "daemon.log");
        ASSERT_TRUE(daemon_->start());
    }
    /// The HTTP port, once the daemon has written it (bounded).
    int httpPort() {
        const auto deadline = Clock::now() + scaled(60s);
        while (Clock::now() < deadline) {
            const std::string t = readText(state() / "http.port");
            if (!t.empty() && t.back() == '\n')
                return std::stoi(t);
            if (daemon_->poll())
                break;
            std::this_thread::sleep_for(20ms); // polling for the daemon's port file
        }
        ADD_FAILURE() << "the daemon did not start its HTTP API";
        return 0;
    }
    nlohmann::json get(int port, const std::string& path) {
        httplib::Client cli("127.0.0.1", port);
        cli.set_read_timeout(10, 0);
        auto r = cli.Get(path);
        if (!r || r->status != 200) {
            ADD_FAILURE() << "GET " << path << " failed";
            return {};
        }
        return nlohmann::json::parse(r->body);
    }
    /// Run 1's record, or null while the daemon has not journaled it yet (404: `--plan` is
    /// queued after the API starts, so a poll may come first) or cannot answer at this moment.
    nlohmann::json runOne(int port) {
        httplib::Client cli("127.0.0.1", port);
        cli.set_read_timeout(10, 0);
        auto r = cli.Get("/api/runs/1");
        if (!r || r->status == 404)
            return nullptr;
        if (r->status != 200) {
            ADD_FAILURE() << "GET /api/runs/1: " << r->status << " " << r->body;
            return nullptr;
        }
        return nlohmann::json::parse(r->body);
    }
    /// Waits (bounded) until run 1 is in one of `states`; returns its record.
    nlohmann::json waitRun(int port, const std::set<std::string>& states,
                           std::chrono::seconds limit = 180s) {
        const auto deadline = Clock::now() + scaled(limit);
        nlohmann::json run;
        while (Clock::now() < deadline) {
            run = runOne(port);
            if (run.is_object() && states.count(run.value("state", "")) != 0)
                return run;
            std::this_thread::sleep_for(100ms); // polling the daemon's API
        }
        ADD_FAILURE() << "run 1 did not reach the expected state: " << run.dump();
        return run;
    }
    int doneCount(int port) {
        const nlohmann::json run = runOne(port);
        return run.is_object() ? run.value("done", 0) : 0;
    }
    void waitDone(int port, int n) {
        const auto deadline = Clock::now() + scaled(120s);
        while (doneCount(port) < n && Clock::now() < deadline)
            std::this_thread::sleep_for(50ms);
        ASSERT_GE(doneCount(port), n);
    }

    /// The journal and files after the daemon has stopped: consistent, every referenced file
    /// complete; `final`: the run is finished, each section captured and registered once.
    void checkStored(bool final) {
        auto j = daemon::Journal::open(state() / "journal.sqlite");
        ASSERT_TRUE(j) << j.error().message;
        auto integrity = (*j)->checkIntegrity();
        ASSERT_TRUE(integrity) << integrity.error().message;
        auto runs = (*j)->runs();
        ASSERT_TRUE(runs);
        if (runs->empty()) {
            ASSERT_FALSE(final);
            return;
        }
        ASSERT_EQ(runs->size(), 1u) << "a restart never queues the plan again";
        auto sections = (*j)->sections(runs->front().id);
        ASSERT_TRUE(sections);
        ASSERT_EQ(sections->size(), static_cast<std::size_t>(kSections)) << "no section lost";
        std::set<fs::path> referenced;
        for (const auto& s : *sections) {
            SCOPED_TRACE(s.name);
            auto caps = (*j)->captures(s.id);
            ASSERT_TRUE(caps);
            ASSERT_LE(caps->size(), 1u) << "captured twice";
            for (const auto& c : *caps) {
                referenced.insert(c.imagePath);
                auto img = daemon::readOmeTiff(state() / c.imagePath);
                ASSERT_TRUE(img) << "referenced image unreadable: " << img.error().message;
                EXPECT_EQ(img->image.cols, 640);
                EXPECT_NEAR(img->info.stage.xUm, s.xUm, 2.0);
                auto regs = (*j)->registrations(s.id);
                ASSERT_TRUE(regs);
                ASSERT_LE(regs->size(), 1u) << "registered twice";
                for (const auto& r : *regs)
                    EXPECT_TRUE(fs::exists(state() / r.overlayPath)) << r.overlayPath;
                if (final) {
                    ASSERT_EQ(regs->size(), 1u) << "every capture registered";
                }
            }
            if (final) {
                EXPECT_EQ(caps->size(), 1u);
                const std::string st = daemon::toString(s.state);
                EXPECT_TRUE(st == "registered" || st == "damaged") << st;
            }
        }
        if (final) {
            EXPECT_EQ(std::string(daemon::toString(runs->front().state)),
                      "finished"); // a const char*: compare the text, not the address
            // No temporary file left, and no complete image that the journal does not know.
            for (const auto& e : fs::recursive_directory_iterator(state() / "runs")) {
                const std::string n = e.path().filename().string();
                EXPECT_FALSE(core::isAtomicTemporaryName(n) || n.ends_with(".partial") ||
                             n.find(".tmp-") != std::string::npos)
                    << e.path();
                if (n.ends_with(".ome.tif")) {
                    EXPECT_TRUE(referenced.count(fs::relative(e.path(), state())) == 1)
                        << "orphan " << e.path();
                }
            }
        }
    }

    fs::path dir_;
    std::unique_ptr<sim::ModbusStageServer> server_;
    std::unique_ptr<DaemonProcess> daemon_;
};

TEST_F(DaemonProcessTest, KilledAtRandomMomentsItResumesWithoutLosingOrDuplicatingAnything) {
    writeStation();
    const unsigned seed = 20261122;
    std::mt19937 rng(seed);
    std::uniform_int_distribution<int> delayMs(300, 4'000);
    int kills = 0;
    for (int round = 0; round < 10; ++round) {
        startDaemon(round == 0);
        if (round == 0) {
            // The plan given on the command line is journaled once the API is up; a kill before
            // that takes the unaccepted plan with the process, which is not what this test is
            // about. Under load (the first daemons of a fresh-clone CI run) the first random
            // moment came before it: no run was ever stored and the test failed.
            const int port = httpPort();
            ASSERT_GT(port, 0);
            waitRun(port, {"running", "paused", "finished"});
        }
        const int delay = delayMs(rng);
        std::this_thread::sleep_for(
            scaled(std::chrono::milliseconds(delay))); // the random moment of the kill
        if (daemon_->poll())
            break; // it finished on its own: nothing left to kill
        daemon_->killHard();
        ++kills;
        SCOPED_TRACE("after kill " + std::to_string(kills) + " at " + std::to_string(delay) +
                     " ms (seed " + std::to_string(seed) + ")");
        checkStored(false);
        if (HasFatalFailure())
            return;
    }
    EXPECT_GE(kills, 5);
    // Restarted for good: it finishes the run and exits.
    startDaemon(false, {}, true);
    ASSERT_EQ(daemon_->waitExit(300s), 0) << "the last daemon did not finish the run";
    checkStored(true);

    auto j = daemon::Journal::open(state() / "journal.sqlite");
    ASSERT_TRUE(j);
    auto alerts = (*j)->alerts(false);
    ASSERT_TRUE(alerts);
    int restarted = 0, damaged = 0;
    for (const auto& a : *alerts) {
        restarted += a.kind == daemon::AlertKind::Restarted;
        damaged += a.kind == daemon::AlertKind::Damaged;
    }
    EXPECT_GE(restarted, 1) << "a run interrupted by a kill raises a 'restarted' alert";
    EXPECT_EQ(damaged, 1) << "the torn section alerted once";
    std::cout << "[ crash    ] " << kills << " kills (seed " << seed << "), " << restarted
              << " restarts during the run; all " << kSections << " sections stored once\n";
}

TEST_F(DaemonProcessTest, NotifiesSystemdAndStopsWatchdogPingsWhileAMoveHangs) {
    writeStation("", "watchdog_stall_s = 2\n", 8);
    NotifyRecorder notify;
    ASSERT_TRUE(notify.bound());
    const auto t0 = Clock::now();
    startDaemon(false, {"NOTIFY_SOCKET=" + notify.path().string(), "WATCHDOG_USEC=1000000"});
    ASSERT_TRUE(notify.waitFor("READY=1", t0, 60s)) << "READY=1 once devices and journal are up";
    const int port = httpPort();
    ASSERT_GT(port, 0);
    // Idle is legitimate: pings every half interval.
    const auto idleFrom = Clock::now();
    ASSERT_TRUE(notify.waitFor("WATCHDOG=1", idleFrom, 5s));
    ASSERT_TRUE(notify.waitFor("WATCHDOG=1", Clock::now(), 5s));

    // The X drive never reports in position: the first move hangs until its 8 s timeout.
    server_->setStall(1, true);
    httplib::Client cli("127.0.0.1", port);
    httplib::Headers auth{{"Authorization", std::string("Bearer ") + kToken}};
    auto sub = cli.Post("/api/runs", auth, readText(dir_ / "plan.toml"), "application/toml");
    ASSERT_TRUE(sub);
    ASSERT_EQ(sub->status, 201) << sub->body;
    auto moving = notify.waitFor("moving", idleFrom, 30s);
    ASSERT_TRUE(moving) << "STATUS= tells what the loop does";
    EXPECT_NE(moving->text.find("STATUS="), std::string::npos);
    EXPECT_NE(moving->text.find("slide"), std::string::npos) << moving->text;
    EXPECT_NE(moving->text.find("section"), std::string::npos) << moving->text;
    // Within the 2 s stall limit (plus a ping period) the pings stop, and stay stopped while
    // the move hangs: from 3 s to 7 s after the move began, not one ping.
    const auto quietFrom = moving->at + 3s;
    std::this_thread::sleep_for(quietFrom + 4s - Clock::now()); // observing the 4 s window
    EXPECT_EQ(notify.count("WATCHDOG=1", quietFrom, quietFrom + 4s), 0)
        << "a hung move must stop the pings";
    EXPECT_EQ(get(port, "/api/runs/1").value("state", ""), "running");

    // The drive is fixed; the hung move times out (8 s) and its retry settles: progress, pings.
    server_->setStall(1, false);
    EXPECT_TRUE(notify.waitFor("WATCHDOG=1", Clock::now(), 20s)) << "pings resume with progress";
    waitDone(port, 1);

    const auto stopAt = Clock::now();
    daemon_->signal(SIGTERM);
    EXPECT_TRUE(notify.waitFor("STOPPING=1", stopAt, 30s));
    EXPECT_EQ(daemon_->waitExit(60s), 0) << "clean stop on SIGTERM";
    EXPECT_TRUE(fs::exists(state() / "clean-stop"));
    checkStored(false);

    // Started again after a clean stop: no "restarted" alert, the run goes on to the end.
    startDaemon(false, {}, true);
    ASSERT_EQ(daemon_->waitExit(300s), 0);
    checkStored(true);
    auto j = daemon::Journal::open(state() / "journal.sqlite");
    ASSERT_TRUE(j);
    auto alerts = (*j)->alerts(false);
    ASSERT_TRUE(alerts);
    const std::vector<daemon::AlertRecord> all = *alerts;
    for (const auto& a : all)
        EXPECT_NE(a.kind, daemon::AlertKind::Restarted) << a.message;
}

TEST_F(DaemonProcessTest, AStageAlarmPausesTheRunUntilTheTechnicianAsksForTheReset) {
    writeStation();
    // The technician is told through a webhook and a command (the alert channels, end to end).
    httplib::Server hook;
    std::mutex hookMutex;
    std::vector<nlohmann::json> hooked;
    hook.Post("/hook", [&](const httplib::Request& req, httplib::Response& res) {
        std::lock_guard lock(hookMutex);
        hooked.push_back(nlohmann::json::parse(req.body, nullptr, false));
        res.status = 204;
    });
    const int hookPort = hook.bind_to_any_port("127.0.0.1");
    ASSERT_GT(hookPort, 0);
    std::thread hookThread([&] { hook.listen_after_bind(); });
    // Stops the receiver on every way out of the test, a failed ASSERT included.
    struct HookGuard {
        httplib::Server& server;
        std::thread& thread;
        ~HookGuard() {
            server.stop();
            if (thread.joinable())
                thread.join();
        }
    } hookGuard{hook, hookThread};
    const fs::path commandOut = dir_ / "command-alerts.txt";
    {
        std::ofstream t(dir_ / "station.toml", std::ios::app);
        t << "[alerts]\njournal = false\n[[alerts.webhook]]\nurl = \"http://127.0.0.1:" << hookPort
          << "/hook\"\n[[alerts.command]]\nargv = [\"/bin/sh\", \"-c\", "
             "\"echo \\\"$SLST_ALERT_ID $SLST_ALERT_KIND\\\" >> "
          << commandOut.string() << "\"]\n";
    }
    // The X drive alarms in its first move, the one to section 1. Arming it once section 1 was
    // done raced the run: captures go ahead of registration, and in CI's sanitizer build every
    // move had been made before the first section was registered (the run finished unpaused).
    server_->armAlarm(1, 0x30);
    startDaemon(true);
    const int port = httpPort();
    ASSERT_GT(port, 0);
    auto run = waitRun(port, {"paused", "finished"});
    ASSERT_EQ(run.value("state", ""), "paused");
    EXPECT_NE(run.value("reason", "").find("stage_fault"), std::string::npos) << run.dump();
    auto alerts = get(port, "/api/alerts?open=1");
    int faults = 0;
    for (const auto& a : alerts)
        faults += a.value("kind", "") == "stage_fault";
    EXPECT_EQ(faults, 1);
    EXPECT_NE(server_->axisState(1).alarmCode, 0u);

    auto slicectl = [port](const std::string& args) {
        return std::system((std::string(SLICECTL_PATH) + " " + args + " --url http://127.0.0.1:" +
                            std::to_string(port) + " --token " + kToken + " > /dev/null")
                               .c_str());
    };
    // Resuming without asking for the reset: the alarm stands and the run pauses again (the
    // resume is journalled before the reply, so the next "paused" is the new one).
    ASSERT_EQ(slicectl("resume 1"), 0);
    run = waitRun(port, {"paused", "finished"}, 60s);
    EXPECT_EQ(run.value("state", ""), "paused");
    EXPECT_NE(server_->axisState(1).alarmCode, 0u) << "an alarm is reset only when asked";

    // The technician cleared the cause and asks for the reset.
    ASSERT_EQ(slicectl("resume 1 --reset-stage-alarm"), 0);
    run = waitRun(port, {"finished"});
    EXPECT_EQ(run.value("done", 0), kSections);
    EXPECT_EQ(server_->axisState(1).alarmCode, 0u);
    const auto journalled = get(port, "/api/alerts");
    daemon_->signal(SIGTERM);
    ASSERT_EQ(daemon_->waitExit(60s), 0);
    checkStored(true);

    // Every journalled alert went out through both channels (the daemon drains them on stop).
    hook.stop();
    hookThread.join();
    std::multiset<std::string> expected, byHook, byCommand;
    for (const auto& a : journalled)
        expected.insert(std::to_string(a["id"].get<std::int64_t>()) + " " +
                        a["kind"].get<std::string>());
    for (const auto& a : hooked)
        byHook.insert(std::to_string(a["id"].get<std::int64_t>()) + " " +
                      a["kind"].get<std::string>());
    std::ifstream in(commandOut);
    for (std::string line; std::getline(in, line);)
        byCommand.insert(line);
    EXPECT_GE(journalled.size(), 4u) << "stage_fault, two pauses, finished";
    EXPECT_EQ(byHook, expected);
    EXPECT_EQ(byCommand, expected);
}

TEST_F(DaemonProcessTest, DroppedCorruptBusyAndSlowModbusRepliesAreRetriedWithoutPausing) {
    writeStation();
    startDaemon(true);
    const int port = httpPort();
    ASSERT_GT(port, 0);
    const std::uint64_t before = server_->requestCount();
    waitDone(port, 1);
    server_->injectReplyFault(sim::ReplyFault::Drop, 2);
    waitDone(port, 2);
    server_->injectReplyFault(sim::ReplyFault::Exception, 2);
    waitDone(port, 3);
    server_->injectReplyFault(sim::ReplyFault::Corrupt, 1);
    waitDone(port, 4);
    server_->injectReplyFault(sim::ReplyFault::Slow, 1, 500ms);
    auto run = waitRun(port, {"paused", "finished", "failed"});
    EXPECT_EQ(run.value("state", ""), "finished") << run.dump();
    for (const auto& a : get(port, "/api/alerts"))
        EXPECT_NE(a.value("kind", ""), "stage_fault") << a.value("message", "");
    EXPECT_GT(server_->requestCount(), before);
    daemon_->signal(SIGTERM);
    ASSERT_EQ(daemon_->waitExit(60s), 0);
    checkStored(true);
}

// Issue 20: hostile station files and plans, through the real daemon. Before the fix a deep plan
// overflowed the stack (SIGSEGV), x_um = 1e400 ended in std::terminate (SIGABRT) at start and
// in a 500 through the API, and a misspelt station key was ignored.
TEST_F(DaemonProcessTest, HostileStationFilesAndPlansAreRefusedWithAMessageAndNeverCrashIt) {
    const auto expectRefusedAtStart = [&](const std::string& needle) {
        startDaemon(false);
        EXPECT_EQ(daemon_->waitExit(60s), 2) << "refused with exit 2, not a crash";
        const std::string log = readText(dir_ / "daemon.log");
        EXPECT_NE(log.find(needle), std::string::npos) << log;
        fs::remove(dir_ / "daemon.log");
    };
    std::string station = stationToml(server_->tcpPort(), "", "", 60);
    station.replace(station.find("speed_um_per_s"), 14, "speeed_um_per_s");
    writeText(dir_ / "station.toml", station);
    expectRefusedAtStart(
        "stage: unknown key \"speeed_um_per_s\"; did you mean \"speed_um_per_s\"?");
    writeStation("min_free_mbb = 3\n");
    expectRefusedAtStart("scan: unknown key \"min_free_mbb\"; did you mean \"min_free_mb\"?");
    writeStation("", "http_bnd = \"0.0.0.0\"\n");
    expectRefusedAtStart("daemon: unknown key \"http_bnd\"; did you mean \"http_bind\"?");

    writeStation();
    std::string deep = R"({"name": "deep", "slides": )";
    deep += std::string(300'000, '[') + std::string(300'000, ']') + "}";
    const std::string overflow =
        R"({"name": "big", "slides": [{"sections": [{"x_um": 1e400, "y_um": 0}]}]})";
    for (const auto& [text, needle] : {std::pair{deep, std::string("nested deeper than 64 levels")},
                                       std::pair{overflow, std::string("number overflow")}}) {
        writeText(dir_ / "plan.json", text);
        daemon_ = std::make_unique<DaemonProcess>(
            std::vector<std::string>{"--config", (dir_ / "station.toml").string(), "--state-dir",
                                     state().string(), "--plan", (dir_ / "plan.json").string()},
            std::vector<std::string>{}, dir_ / "daemon.log");
        ASSERT_TRUE(daemon_->start());
        EXPECT_EQ(daemon_->waitExit(120s), 2) << needle;
        const std::string log = readText(dir_ / "daemon.log");
        EXPECT_NE(log.find(needle), std::string::npos) << log;
        fs::remove(dir_ / "daemon.log");
    }

    // The same bodies, and plans the station cannot scan, through the API: 400 with the reason.
    startDaemon(false);
    const int port = httpPort();
    ASSERT_GT(port, 0);
    httplib::Client cli("127.0.0.1", port);
    cli.set_read_timeout(30, 0);
    httplib::Headers auth{{"Authorization", std::string("Bearer ") + kToken}};
    const auto submit = [&](const std::string& body, const char* type) {
        auto r = cli.Post("/api/runs", auth, body, type);
        return r ? std::pair{r->status, r->body} : std::pair{-1, std::string("(no reply)")};
    };
    const std::string wide = "name = \"wide\"\n[[slides]]\n[[slides.sections]]\nname = \"w\"\nx_um "
                             "= 10000\ny_um = 45000\nheight_um = 12000\n";
    const std::string longName = "name = \"long\"\n[[slides]]\n[[slides.sections]]\nname = \"" +
                                 std::string(300, 'n') + "\"\nx_um = 10000\ny_um = 10000\n";
    const std::string typo = "name = \"typo\"\n[[slides]]\n[[slides.sections]]\nx_um = 10000\ny_um "
                             "= 10000\nwidht_um = 5\n";
    for (const auto& [body, type, needle] :
         {std::tuple{deep, "application/json", std::string("nested deeper than 64 levels")},
          std::tuple{overflow, "application/json", std::string("number overflow")},
          std::tuple{wide, "application/toml",
                     std::string("slides[0].sections[0].y_um: section \\\"w\\\" on slide-1 reaches "
                                 "Y 39000 .. 51000 um")},
          std::tuple{longName, "application/toml", std::string("300 bytes is longer than the 64")},
          std::tuple{typo, "application/toml", std::string("did you mean \\\"width_um\\\"?")}}) {
        const auto [status, reply] = submit(body, type);
        EXPECT_EQ(status, 400) << needle << ": " << reply.substr(0, 300);
        EXPECT_NE(reply.find(needle), std::string::npos) << reply.substr(0, 300);
    }
    EXPECT_FALSE(daemon_->poll()) << "the daemon is still running";
    EXPECT_TRUE(get(port, "/api/runs").empty()) << "nothing was queued";
    daemon_->signal(SIGTERM);
    EXPECT_EQ(daemon_->waitExit(60s), 0);
}

} // namespace
} // namespace slicestation::test
