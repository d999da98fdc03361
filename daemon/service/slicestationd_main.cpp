// slicestationd: the station daemon. Opens the devices named in the station file, the journal
// and the atlas, serves the HTTP API, and scans the queued runs until SIGTERM.
// Only this program logs; lines carry sd-daemon priority prefixes for the systemd journal.
#include "slicestation/daemon/alerts/alert_channels.hpp"

#include "slicestation/core/atomic_file.hpp"
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/config/station_config.hpp"
#include "slicestation/daemon/devices/devices.hpp"
#include "slicestation/daemon/http/http_api.hpp"
#include "slicestation/daemon/service/systemd_notifier.hpp"
#include "slicestation/daemon/station/station.hpp"
#include "slicestation/daemon/version.hpp"

#include <CLI/CLI.hpp>

#include <atomic>
#include <csignal>
#include <cstdlib>
#include <iostream>
#include <mutex>
#include <pthread.h>

namespace {

using namespace slicestation;
using namespace slicestation::daemon;

int fail(const std::string& what, const core::Error& e) {
    std::cerr << "<3>slicestationd: " << what << ": " << e.message << std::endl;
    return e.code == core::ErrorCode::InvalidArgument || e.code == core::ErrorCode::NotFound ? 2
                                                                                             : 1;
}

/// The camera looks where the stage last settled: the simulated camera renders from that.
struct LastStage {
    std::mutex mutex;
    hw::StagePosition position;
    void store(const hw::StagePosition& p) {
        std::lock_guard lock(mutex);
        position = p;
    }
    hw::StagePosition load() {
        std::lock_guard lock(mutex);
        return position;
    }
};

/// Opens the configured stage and camera into `parts`, saying loudly when one is simulated.
/// \return an exit code when one cannot be opened.
std::optional<int> openDevices(const StationConfig& station, StationParts& parts,
                               const std::shared_ptr<LastStage>& lastStage) {
    auto stage = openStage(station.stage, parts.simulatedStage);
    if (!stage)
        return fail("stage", stage.error());
    parts.stage = std::move(*stage);
    if (auto p = parts.stage->position(std::chrono::milliseconds(2000)))
        lastStage->store(*p);
    auto camera = openCamera(
        station.camera, [lastStage] { return lastStage->load(); }, parts.simulatedCamera);
    if (!camera)
        return fail("camera", camera.error());
    parts.camera = std::move(*camera);
    if (parts.simulatedStage)
        std::cerr << "<4>slicestationd: SIMULATED stage (stage.driver = \"sim\")" << std::endl;
    if (parts.simulatedCamera)
        std::cerr << "<4>slicestationd: SIMULATED camera (camera.driver = \"sim\")" << std::endl;
    parts.stageMoved = [lastStage](const hw::StagePosition& p) { lastStage->store(p); };
    return std::nullopt;
}

std::unique_ptr<AlertDispatcher>
startAlertDelivery(const AlertSettings& settings,
                   std::vector<std::unique_ptr<AlertChannelSink>> sinks) {
    // Outward alert delivery ([alerts]), set up before the station so that it also carries the
    // "restarted" alert raised while the station opens its journal, and declared before it so
    // that it outlives the station's threads. A channel that gives up is logged here; the alert
    // itself stays open in the journal. Without journald (a container) the journal channel
    // fails for every alert: that is said once.
    auto journalFailureLogged = std::make_shared<std::atomic<bool>>(false);
    auto alerts = std::make_unique<AlertDispatcher>(
        settings, std::move(sinks),
        [journalFailureLogged](const std::string& channel, const AlertRecord& a,
                               const core::Error& e) {
            if (channel == "journal" && journalFailureLogged->exchange(true))
                return;
            // The message names the channel.
            std::cerr << "<4>slicestationd: alert " << a.id << " (" << toString(a.kind)
                      << ") not delivered: " << e.message
                      << (channel == "journal" ? " (not repeated)" : "") << std::endl;
        });
    {
        std::string names;
        for (const auto& n : alerts->channelNames())
            names += (names.empty() ? "" : ", ") + n;
        std::cerr << "<6>slicestationd: alert channels: "
                  << (names.empty() ? "none (journal disabled)" : names) << " (min severity "
                  << toString(settings.minSeverity) << ", " << settings.retries << " retries, "
                  << settings.maxPerWindow << "/min per channel)" << std::endl;
    }
    return alerts;
}

/// Signals are taken synchronously by the main thread; every other thread has them blocked.
/// \return SIGTERM and SIGINT, for waitForStop.
sigset_t blockStopSignals() {
    sigset_t signals;
    sigemptyset(&signals);
    sigaddset(&signals, SIGTERM);
    sigaddset(&signals, SIGINT);
    pthread_sigmask(SIG_BLOCK, &signals, nullptr);
    std::signal(SIGPIPE, SIG_IGN);
    return signals;
}

struct Options {
    std::string configFile, stateDirOpt;
    std::vector<std::string> plans;
    std::optional<int> httpPort;
    bool exitWhenIdle = false;
};

/// The command line. \return an exit code when the program should end (--help, bad usage).
std::optional<int> parseOptions(int argc, char** argv, Options& o) {
    CLI::App app{"slicestationd: the slide-scanning station daemon"};
    app.set_version_flag("--version",
                         std::string("slicestationd ") + slicestation::daemon::kVersion);
    app.add_option("--config", o.configFile,
                   "Station file (TOML): [stage], [camera], [daemon], [scan]")
        ->required();
    app.add_option("--state-dir", o.stateDirOpt,
                   "State directory (default: $STATE_DIRECTORY, then daemon.state_dir)");
    app.add_option("--plan", o.plans, "Submit this scan plan at start (TOML or JSON); repeatable");
    app.add_option("--http-port", o.httpPort, "Override daemon.http_port (0: any free port)");
    app.add_flag("--exit-when-idle", o.exitWhenIdle,
                 "Exit once no run is left to scan (demo, benchmark)");
    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        return app.exit(e);
    }
    return std::nullopt;
}

/// --state-dir, else $STATE_DIRECTORY (systemd), else daemon.state_dir; empty when none.
std::filesystem::path stateDirectory(const std::string& option,
                                     const std::filesystem::path& configured) {
    if (!option.empty())
        return option;
    if (const char* env = std::getenv("STATE_DIRECTORY"); env && *env)
        return env;
    return configured;
}

/// Until SIGTERM or SIGINT, or (exitWhenIdle) until no run is left to scan.
void waitForStop(const sigset_t& signals, Station& s, bool exitWhenIdle) {
    for (;;) {
        const timespec wait{0, 200'000'000};
        const int sig = sigtimedwait(&signals, nullptr, &wait);
        if (sig == SIGTERM || sig == SIGINT) {
            std::cerr << "<5>slicestationd: " << (sig == SIGTERM ? "SIGTERM" : "SIGINT")
                      << ": stopping" << std::endl;
            return;
        }
        if (exitWhenIdle && s.idle()) {
            auto next = s.journal().nextRun();
            if (next && !*next)
                return;
        }
    }
}

} // namespace

int main(int argc, char** argv) {
    Options opt;
    if (auto rc = parseOptions(argc, argv, opt))
        return *rc;
    const sigset_t signals = blockStopSignals();

    auto station = loadStationConfig(opt.configFile);
    if (!station)
        return fail("station file", station.error());
    auto doc = readDocument(opt.configFile);
    if (!doc)
        return fail("station file", doc.error());
    auto settings = parseDaemonSettings(*doc, opt.configFile);
    if (!settings)
        return fail("station file", settings.error());
    if (opt.httpPort)
        settings->httpPort = *opt.httpPort;
    auto alertSettings = parseAlertSettings(*doc, opt.configFile);
    if (!alertSettings)
        return fail("station file", alertSettings.error());
    auto alertSinks = makeAlertSinks(*alertSettings);
    if (!alertSinks)
        return fail("station file", alertSinks.error());

    const std::filesystem::path stateDir = stateDirectory(opt.stateDirOpt, settings->stateDir);
    if (stateDir.empty())
        return fail(
            "state directory",
            core::makeError(core::ErrorCode::InvalidArgument,
                            "none given: use --state-dir, $STATE_DIRECTORY or daemon.state_dir"));

    SystemdNotifier notifier = SystemdNotifier::fromEnvironment();
    notifier.status("opening devices");

    auto lastStage = std::make_shared<LastStage>();
    StationParts parts;
    if (auto rc = openDevices(*station, parts, lastStage))
        return *rc;
    parts.settings = *settings;
    parts.stateDir = stateDir;

    core::SteadyClock clock;
    std::unique_ptr<ProgressWatchdog> watchdog =
        notifier.watchdogInterval()
            ? std::make_unique<ProgressWatchdog>(notifier, settings->watchdogStall, clock)
            : nullptr;
    parts.watchdog = watchdog.get();
    parts.status = [&notifier](const std::string& s) { notifier.status(s); };

    auto alerts = startAlertDelivery(*alertSettings, std::move(*alertSinks));
    parts.alertChannels.push_back([d = alerts.get()](const AlertRecord& a) { d->post(a); });
    auto st = Station::create(std::move(parts));
    if (!st) {
        alerts->stop(std::chrono::seconds(5));
        return fail("station", st.error());
    }
    Station& s = **st;
    auto api = HttpApi::start(s, settings->httpBind, settings->httpPort, settings->token);
    if (!api)
        return fail("HTTP API", api.error());
    std::cerr << "<6>slicestationd: state " << stateDir << ", atlas " << s.atlas().dir << " ("
              << s.atlas().slices.size() << " slices), HTTP on " << settings->httpBind << ":"
              << (*api)->port() << std::endl;

    for (const auto& plan : opt.plans) {
        auto pd = readDocument(plan);
        if (!pd)
            return fail("plan", pd.error());
        auto id = s.submitPlan(*pd, plan);
        if (!id)
            return fail("plan", id.error());
        std::cerr << "<6>slicestationd: plan " << plan << " queued as run " << *id << std::endl;
    }
    // The port file says "ready": written once the plans given at start are queued, so that a
    // client that reads it finds them.
    (void)core::writeFileAtomically(stateDir / "http.port", std::to_string((*api)->port()) + "\n");

    s.start();
    notifier.ready();

    waitForStop(signals, s, opt.exitWhenIdle);
    notifier.stopping();
    notifier.status("stopping: stage halted, finishing the current transaction");
    if (watchdog)
        watchdog->stop();
    (*api)->stop();
    s.stop();
    // After the station: its last alerts (a paused run) still get out, within 5 s.
    alerts->stop(std::chrono::seconds(5));
    std::cerr << "<6>slicestationd: stopped" << std::endl;
    return 0;
}
