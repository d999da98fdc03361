// SystemdNotifier and ProgressWatchdog against a fake NOTIFY_SOCKET (a unix datagram socket
// made here), with a manual clock: no sleeps, every wait is on an event with a deadline.
#include "slicestation/daemon/service/systemd_notifier.hpp"

#include "fake_notify_socket.hpp"
#include "slicestation/core/unique_fd.hpp"

#include <gtest/gtest.h>

#include <poll.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <condition_variable>
#include <cstring>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace slicestation::test {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono_literals;

/// Sets environment variables for one test and restores them after.
class ScopedEnv {
public:
    void set(const char* name, const std::string& value) {
        remember(name);
        ::setenv(name, value.c_str(), 1);
    }
    void unset(const char* name) {
        remember(name);
        ::unsetenv(name);
    }
    ~ScopedEnv() {
        for (auto& [name, old] : saved_) {
            if (old)
                ::setenv(name.c_str(), old->c_str(), 1);
            else
                ::unsetenv(name.c_str());
        }
    }

private:
    void remember(const char* name) {
        for (auto& s : saved_)
            if (s.first == name)
                return;
        const char* v = std::getenv(name);
        saved_.emplace_back(name, v ? std::optional<std::string>(v) : std::nullopt);
    }
    std::vector<std::pair<std::string, std::optional<std::string>>> saved_;
};

/// Time that moves only when the test says so. sleepUntil blocks until the time is reached or
/// the stop signal is raised; waitForSleeper() tells the test that the sleeping thread has
/// seen the latest advance() and is waiting again (so everything it did is observable).
class ManualClock final : public core::Clock {
public:
    core::TimePoint now() const override {
        std::lock_guard lock(mutex_);
        return now_;
    }
    bool sleepUntil(core::TimePoint t, const core::StopSignal& stop) override {
        std::unique_lock lock(mutex_);
        ++sleepers_;
        while (now_ < t && !stop.raised()) {
            seenGeneration_ = generation_;
            cv_.notify_all();
            // StopSignal has its own condition variable: check it every few ms of real time.
            cv_.wait_for(lock, 2ms);
        }
        --sleepers_;
        return !stop.raised();
    }
    void advance(std::chrono::nanoseconds d) {
        std::lock_guard lock(mutex_);
        now_ += d;
        ++generation_;
        cv_.notify_all();
    }
    /// True once a thread sleeps having seen the latest advance().
    bool waitForSleeper(std::chrono::milliseconds timeout = kEventDeadline) {
        std::unique_lock lock(mutex_);
        return cv_.wait_for(lock, timeout,
                            [&] { return sleepers_ > 0 && seenGeneration_ == generation_; });
    }

private:
    mutable std::mutex mutex_;
    std::condition_variable cv_;
    core::TimePoint now_{std::chrono::seconds(1000)};
    std::uint64_t generation_ = 0;
    std::uint64_t seenGeneration_ = ~std::uint64_t{0};
    int sleepers_ = 0;
};

class Notify : public ::testing::Test {
protected:
    void SetUp() override {
        ASSERT_TRUE(socket_.bound());
        env_.set("NOTIFY_SOCKET", socket_.path().string());
        env_.unset("WATCHDOG_USEC");
        env_.unset("WATCHDOG_PID");
    }
    FakeNotifySocket socket_;
    ScopedEnv env_;
};

TEST_F(Notify, ReadyStatusStoppingReloadingAndErrno) {
    auto n = daemon::SystemdNotifier::fromEnvironment();
    ASSERT_TRUE(n.enabled());
    EXPECT_FALSE(n.watchdogInterval());
    n.ready();
    EXPECT_EQ(socket_.receive(), "READY=1");
    n.status("slide 3/12 section 5 tile 14/40 AF ok");
    EXPECT_EQ(socket_.receive(), "STATUS=slide 3/12 section 5 tile 14/40 AF ok");
    n.status("two\nlines READY=1");
    EXPECT_EQ(socket_.receive(), "STATUS=two lines READY=1") << "a newline must not inject";
    n.reloading();
    const auto reloading = socket_.receive();
    ASSERT_TRUE(reloading);
    EXPECT_EQ(reloading->rfind("RELOADING=1\nMONOTONIC_USEC=", 0), 0u) << *reloading;
    n.errnoStatus(5);
    EXPECT_EQ(socket_.receive(), "ERRNO=5");
    n.stopping();
    EXPECT_EQ(socket_.receive(), "STOPPING=1");
    EXPECT_EQ(n.sendFailures(), 0u);
}

TEST_F(Notify, WatchdogIntervalFromEnvironment) {
    env_.set("WATCHDOG_USEC", "30000000");
    env_.set("WATCHDOG_PID", std::to_string(::getpid()));
    auto n = daemon::SystemdNotifier::fromEnvironment();
    ASSERT_TRUE(n.watchdogInterval());
    EXPECT_EQ(*n.watchdogInterval(), 30s);

    env_.set("WATCHDOG_PID", std::to_string(::getpid() + 1)); // meant for another process
    EXPECT_FALSE(daemon::SystemdNotifier::fromEnvironment().watchdogInterval());
    env_.unset("WATCHDOG_PID"); // systemd may omit it
    EXPECT_TRUE(daemon::SystemdNotifier::fromEnvironment().watchdogInterval());
    env_.set("WATCHDOG_USEC", "soon");
    EXPECT_FALSE(daemon::SystemdNotifier::fromEnvironment().watchdogInterval());
}

TEST_F(Notify, SendFailuresAreCountedNotThrown) {
    auto n = daemon::SystemdNotifier::fromEnvironment();
    env_.set("NOTIFY_SOCKET", (socket_.path().parent_path() / "gone").string());
    n.ready();
    n.watchdogPing();
    EXPECT_EQ(n.sendFailures(), 2u);
}

TEST(NotifyOutsideSystemd, EverythingIsANoOp) {
    ScopedEnv env;
    env.unset("NOTIFY_SOCKET");
    env.set("WATCHDOG_USEC", "1000000");
    auto n = daemon::SystemdNotifier::fromEnvironment();
    EXPECT_FALSE(n.enabled());
    EXPECT_FALSE(n.watchdogInterval());
    n.ready();
    n.status("x");
    n.watchdogPing();
    n.stopping();
    n.reloading();
    EXPECT_EQ(n.sendFailures(), 0u);
    ManualClock clock;
    daemon::ProgressWatchdog wd(n, 1s, clock);
    EXPECT_FALSE(wd.active());
    wd.progress();
    wd.setIdle(true);
    wd.stop();
    EXPECT_EQ(wd.pingsSent(), 0u);
}

TEST_F(Notify, NoWatchdogSecMeansNoThread) {
    auto n = daemon::SystemdNotifier::fromEnvironment();
    ManualClock clock;
    daemon::ProgressWatchdog wd(n, 1s, clock);
    EXPECT_FALSE(wd.active());
    EXPECT_FALSE(socket_.pending());
}

class Watchdog : public Notify {
protected:
    void SetUp() override {
        Notify::SetUp();
        env_.set("WATCHDOG_USEC", "2000000"); // WatchdogSec=2s: ping every 1 s
        env_.set("WATCHDOG_PID", std::to_string(::getpid()));
        notifier_ = daemon::SystemdNotifier::fromEnvironment();
        ASSERT_EQ(notifier_.watchdogInterval(), std::chrono::microseconds(2s));
    }
    /// Advances the clock by one ping period and waits until the watchdog has acted on it.
    void tick() {
        clock_.advance(1s);
        ASSERT_TRUE(clock_.waitForSleeper());
    }
    void expectPing() { EXPECT_EQ(socket_.pending(), "WATCHDOG=1"); }
    void expectSilence() { EXPECT_EQ(socket_.pending(), std::nullopt); }
    daemon::SystemdNotifier notifier_;
    ManualClock clock_;
};

TEST_F(Watchdog, PingsWhileProgressStopsDuringAHangResumesAfter) {
    daemon::ProgressWatchdog wd(notifier_, 3s, clock_);
    ASSERT_TRUE(wd.active());
    ASSERT_TRUE(clock_.waitForSleeper());
    expectPing(); // at start: progress counts as just made
    for (int i = 0; i < 3; ++i) {
        wd.progress(); // a move settled, a frame came
        tick();
        expectPing();
    }
    // Injected hang: a move that never settles, no progress. Within the stall limit (3 s after
    // the last progress) the pings go on, then stop for good.
    tick();
    expectPing(); // 2 s since the last progress
    tick();
    expectPing(); // exactly 3 s: still within the limit
    for (int i = 0; i < 5; ++i) {
        tick();
        expectSilence();
    }
    EXPECT_EQ(wd.pingsSent(), 6u);
    // The loop recovers (e.g. after the stage driver's own timeout): pings resume.
    wd.progress();
    tick();
    expectPing();
    wd.stop();
    wd.stop(); // idempotent
    expectSilence();
}

TEST_F(Watchdog, IdleKeepsPingingWithoutProgress) {
    daemon::ProgressWatchdog wd(notifier_, 2s, clock_);
    ASSERT_TRUE(clock_.waitForSleeper());
    expectPing();
    wd.setIdle(true); // no run queued
    for (int i = 0; i < 10; ++i) {
        tick();
        expectPing();
    }
    wd.setIdle(false); // a run starts: a fresh stall window, then the hang rule applies
    tick();
    expectPing();
    tick();
    expectPing();
    tick();
    expectSilence();
}

TEST_F(Watchdog, StopEndsTheThreadPromptly) {
    auto wd = std::make_unique<daemon::ProgressWatchdog>(notifier_, 3s, clock_);
    ASSERT_TRUE(clock_.waitForSleeper());
    expectPing();
    wd.reset(); // the destructor stops and joins while the thread is asleep
    clock_.advance(10s);
    expectSilence();
}

} // namespace
} // namespace slicestation::test
