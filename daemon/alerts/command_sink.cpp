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

namespace {

/// The daemon's environment, minus stale SLST_ALERT_* entries, plus this alert.
std::vector<std::string> alertEnvironment(const AlertRecord& alert) {
    std::vector<std::string> env;
    for (char** e = environ; e && *e; ++e)
        if (!std::string_view(*e).starts_with("SLST_ALERT_"))
            env.emplace_back(*e);
    env.push_back("SLST_ALERT_ID=" + std::to_string(alert.id));
    env.push_back(std::string("SLST_ALERT_KIND=") + toString(alert.kind));
    env.push_back(std::string("SLST_ALERT_SEVERITY=") + toString(alert.severity));
    env.push_back("SLST_ALERT_MESSAGE=" + alert.message);
    env.push_back("SLST_ALERT_RUN_ID=" + optionalId(alert.runId));
    env.push_back("SLST_ALERT_SECTION_ID=" + optionalId(alert.sectionId));
    env.push_back("SLST_ALERT_RAISED_UTC=" + alert.raisedUtc);
    env.push_back("SLST_ALERT_JSON=" + toJson(alert).dump());
    return env;
}

/// Starts argv[0] (searched in PATH unless it holds a '/') with stdin on /dev/null, a clean
/// signal mask, default dispositions and its own process group. \return its pid.
Result<pid_t> spawnWithEnvironment(std::vector<std::string> argv, std::vector<std::string> env) {
    std::vector<char*> envp, argvp;
    for (auto& e : env)
        envp.push_back(e.data());
    envp.push_back(nullptr);
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
                         std::string("cannot start: ") + std::strerror(rc), rc);
    return pid;
}

} // namespace

Result<void> CommandSink::deliver(const AlertRecord& alert) {
    const std::string what = name();
    if (impl_->cancelled)
        return makeError(ErrorCode::Cancelled, what + ": stopped");

    auto spawned = spawnWithEnvironment(impl_->settings.argv, alertEnvironment(alert));
    if (!spawned)
        return makeError(spawned.error().code, what + ": " + spawned.error().message,
                         spawned.error().sysErrno);
    const pid_t pid = *spawned;

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

} // namespace slicestation::daemon
