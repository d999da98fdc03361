// FaultyStage and SimStage fault behaviour: each error code a stage model returns is provoked.
#include "slicestation/sim/faulty_stage.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <future>
#include <utility>
#include <vector>

namespace slicestation::sim {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;

std::unique_ptr<SimStage> makeSim(std::shared_ptr<core::Clock> clock) {
    SimStageConfig cfg;
    cfg.clock = std::move(clock);
    return SimStage::create(cfg).value();
}

TEST(SimStage, CreateRejectsBadConfig) {
    SimStageConfig cfg;
    cfg.limits.x = {10, 5};
    auto r = SimStage::create(cfg);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    cfg = {};
    cfg.speedUmPerS = 0;
    EXPECT_FALSE(SimStage::create(cfg));
}

TEST(SimStage, MovesTakeTimeOnTheInjectedClock) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto s = makeSim(clock);
    const auto t0 = clock->now();
    ASSERT_TRUE(s->moveTo({20'000, 0, 0}, 10s));
    const double seconds = std::chrono::duration<double>(clock->now() - t0).count();
    // 20 mm at 20 mm/s with 100 mm/s^2 ramps: 1.2 s of motion plus the settle time.
    EXPECT_NEAR(seconds, 1.2 + 0.02, 0.03);
}

// The live position (issue 23): every poll of the wait reports the feedback on the stage clock,
// through FaultyStage too; the positions travel from start to target in order.
TEST(SimStage, MovesReportTheirFeedbackWhileTheyWait) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto s = FaultyStage::create(makeSim(clock), clock).value();
    std::vector<std::pair<double, core::TimePoint>> seen;
    s->setMoveObserver(
        [&](const hw::StagePosition& p, core::TimePoint at) { seen.emplace_back(p.xUm, at); });
    ASSERT_TRUE(s->moveTo({20'000, 0, 0}, 10s));
    // 1.22 s of motion and settling polled every 5 ms.
    ASSERT_GE(seen.size(), 200u);
    EXPECT_EQ(seen.front().first, 0.0);
    EXPECT_NEAR(seen.back().first, 20'000, 1.0);
    for (std::size_t k = 1; k < seen.size(); ++k) {
        EXPECT_GE(seen[k].first, seen[k - 1].first) << k;
        EXPECT_GT(seen[k].second, seen[k - 1].second) << k;
    }
    const auto half =
        std::find_if(seen.begin(), seen.end(), [](const auto& e) { return e.first >= 10'000; });
    ASSERT_NE(half, seen.end());
    // Half way after 0.6 s (a symmetric trapezoid), on the stage clock.
    EXPECT_NEAR(std::chrono::duration<double>(half->second - seen.front().second).count(), 0.6,
                0.01);
}

TEST(SimStage, StallTimesOut) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto s = makeSim(clock);
    s->axis('y').setStall(true);
    auto r = s->moveTo({1000, 1000, 0}, 3s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout);
}

TEST(SimStage, AlarmMidMoveIsReportedAndResetOnlyWhenAsked) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto s = makeSim(clock);
    s->axis('x').armAlarm(0x30);
    auto r = s->moveTo({5000, 0, 0}, 10s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Alarm);
    auto a = s->alarm(1s);
    ASSERT_TRUE(a);
    EXPECT_TRUE(a->active);
    EXPECT_EQ(a->code, 0x30u);
    EXPECT_EQ(a->axis, "x");
    auto again = s->moveTo({100, 0, 0}, 10s); // still in alarm: refused
    ASSERT_FALSE(again);
    EXPECT_EQ(again.error().code, ErrorCode::Alarm);
    ASSERT_TRUE(s->resetAlarm(1s));
    EXPECT_FALSE(s->alarm(1s)->active);
    EXPECT_TRUE(s->moveTo({100, 0, 0}, 10s));
}

TEST(SimStage, FeedbackDriftIsNotSettled) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto s = makeSim(clock);
    s->axis('x').setDriftSteps(25);
    auto r = s->moveTo({1000, 0, 0}, 2s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout);
    EXPECT_NE(r.error().message.find("feedback"), std::string::npos) << r.error().message;
}

TEST(FaultyStage, ScriptedErrorsHappenOnce) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto f = FaultyStage::create(makeSim(clock), clock).value();
    f->failNext(FaultyStage::Op::Position, core::makeError(ErrorCode::IoError, "bad reply"));
    auto p = f->position(1s);
    ASSERT_FALSE(p);
    EXPECT_EQ(p.error().code, ErrorCode::IoError);
    EXPECT_TRUE(f->position(1s));
}

TEST(FaultyStage, StallTimesOutAndStopPreempts) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto f = FaultyStage::create(makeSim(clock), clock).value();
    f->stallMoves(true);
    auto r = f->moveTo({100, 100, 0}, 5s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout);

    auto steady = std::make_shared<core::SteadyClock>();
    auto g = FaultyStage::create(makeSim(steady), steady).value();
    g->stallMoves(true);
    auto* raw = g.get();
    auto fut = std::async(std::launch::async, [raw] { return raw->moveTo({100, 100, 0}, 60s); });
    while (fut.wait_for(10ms) != std::future_status::ready)
        raw->stop();
    auto s = fut.get();
    ASSERT_FALSE(s);
    EXPECT_EQ(s.error().code, ErrorCode::Cancelled);
}

TEST(FaultyStage, AlarmLatchesUntilReset) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto f = FaultyStage::create(makeSim(clock), clock).value();
    f->alarmOnNextMove(0x42);
    EXPECT_EQ(f->moveTo({100, 100, 0}, 5s).error().code, ErrorCode::Alarm);
    EXPECT_EQ(f->moveTo({100, 100, 0}, 5s).error().code, ErrorCode::Alarm);
    EXPECT_EQ(f->alarm(1s)->code, 0x42u);
    ASSERT_TRUE(f->resetAlarm(1s));
    EXPECT_TRUE(f->moveTo({100, 100, 0}, 5s));
}

TEST(FaultyStage, DisconnectAfterNCalls) {
    auto clock = std::make_shared<core::VirtualClock>();
    auto f = FaultyStage::create(makeSim(clock), clock).value();
    f->disconnectAfter(1);
    EXPECT_TRUE(f->position(1s));
    auto r = f->position(1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Disconnected);
}

TEST(FaultyStage, CreateRejectsNull) {
    auto r = FaultyStage::create(nullptr, nullptr);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
}

TEST(StageLimits, NanIsOutOfRange) {
    hw::StageLimits l{{0, 10}, {0, 10}, std::nullopt};
    EXPECT_FALSE(hw::checkWithinLimits(l, {std::nan(""), 1, 0}));
    EXPECT_TRUE(hw::checkWithinLimits(l, {1, 1, 99}));
}

} // namespace
} // namespace slicestation::sim
