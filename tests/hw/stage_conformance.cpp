// Conformance of every hw::Stage model: the contract written in core/stage.hpp.
#include "stage_conformance.hpp"

#include <gtest/gtest.h>

#include <chrono>
#include <future>

namespace slicestation::test {

using namespace std::chrono_literals;
using core::ErrorCode;

std::vector<StageModel> stageModels(); // defined per test executable

class StageConformance : public ::testing::TestWithParam<StageModel> {};

namespace {
hw::StagePosition inside(const hw::StageLimits& l, double fx, double fy) {
    hw::StagePosition p;
    p.xUm = l.x.minUm + fx * (l.x.maxUm - l.x.minUm);
    p.yUm = l.y.minUm + fy * (l.y.maxUm - l.y.minUm);
    p.zUm = l.z ? l.z->minUm + 0.5 * (l.z->maxUm - l.z->minUm) : 0;
    return p;
}
} // namespace

TEST_P(StageConformance, LimitsAreOrdered) {
    auto s = GetParam().make(false);
    ASSERT_TRUE(s);
    const auto l = s->limits();
    EXPECT_LT(l.x.minUm, l.x.maxUm);
    EXPECT_LT(l.y.minUm, l.y.maxUm);
    if (l.z) {
        EXPECT_LT(l.z->minUm, l.z->maxUm);
    }
}

TEST_P(StageConformance, MoveSettlesAtTarget) {
    auto s = GetParam().make(false);
    const auto l = s->limits();
    for (auto [fx, fy] : {std::pair{0.1, 0.2}, std::pair{0.02, 0.05}, std::pair{0.03, 0.01}}) {
        const auto target = inside(l, fx, fy);
        auto r = s->moveTo(target, 10s);
        ASSERT_TRUE(r) << r.error().message;
        EXPECT_NEAR(r->xUm, target.xUm, 2.0);
        EXPECT_NEAR(r->yUm, target.yUm, 2.0);
        if (l.z) {
            EXPECT_NEAR(r->zUm, target.zUm, 2.0);
        }
        auto p = s->position(1s);
        ASSERT_TRUE(p) << p.error().message;
        EXPECT_NEAR(p->xUm, target.xUm, 2.0);
        EXPECT_NEAR(p->yUm, target.yUm, 2.0);
    }
}

TEST_P(StageConformance, MoveOutsideLimitsIsRefusedAndNothingMoves) {
    auto s = GetParam().make(false);
    const auto l = s->limits();
    const auto start = inside(l, 0.05, 0.05);
    ASSERT_TRUE(s->moveTo(start, 10s));
    for (auto bad : {hw::StagePosition{l.x.maxUm + 1, start.yUm, start.zUm},
                     hw::StagePosition{start.xUm, l.y.minUm - 1, start.zUm}}) {
        auto r = s->moveTo(bad, 10s);
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, ErrorCode::OutOfRange);
        EXPECT_NE(r.error().message.find("soft limits"), std::string::npos) << r.error().message;
    }
    if (l.z) {
        auto r = s->moveTo({start.xUm, start.yUm, l.z->maxUm + 1}, 10s);
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, ErrorCode::OutOfRange);
    }
    auto p = s->position(1s);
    ASSERT_TRUE(p);
    EXPECT_NEAR(p->xUm, start.xUm, 2.0);
    EXPECT_NEAR(p->yUm, start.yUm, 2.0);
}

TEST_P(StageConformance, HomeReturnsToOrigin) {
    auto s = GetParam().make(false);
    ASSERT_TRUE(s->moveTo(inside(s->limits(), 0.02, 0.03), 10s));
    auto r = s->home(10s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_NEAR(r->xUm, 0, 2.0);
    EXPECT_NEAR(r->yUm, 0, 2.0);
}

TEST_P(StageConformance, NoAlarmInitiallyAndResetIsHarmless) {
    auto s = GetParam().make(false);
    auto a = s->alarm(1s);
    ASSERT_TRUE(a) << a.error().message;
    EXPECT_FALSE(a->active);
    EXPECT_TRUE(s->resetAlarm(1s));
    EXPECT_TRUE(s->moveTo(inside(s->limits(), 0.01, 0.01), 10s));
}

TEST_P(StageConformance, StopIsIdempotentAndSafeWhenIdle) {
    auto s = GetParam().make(false);
    s->stop();
    s->stop();
    auto r = s->moveTo(inside(s->limits(), 0.02, 0.02), 10s);
    EXPECT_TRUE(r) << r.error().message;
}

TEST_P(StageConformance, StopPreemptsAMoveInProgress) {
    auto s = GetParam().make(true);
    const auto l = s->limits();
    auto* raw = s.get();
    const auto t0 = std::chrono::steady_clock::now();
    auto fut =
        std::async(std::launch::async, [raw, l] { return raw->moveTo(inside(l, 0.9, 0.9), 60s); });
    // Keep asking to stop until the move returns; waits on the future, never sleeps.
    while (fut.wait_for(20ms) != std::future_status::ready) {
        raw->stop();
        ASSERT_LT(std::chrono::steady_clock::now() - t0, 30s) << "stop() did not preempt";
    }
    auto r = fut.get();
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Cancelled) << r.error().message;
    EXPECT_LT(std::chrono::steady_clock::now() - t0, 10s);
    auto p = s->position(1s);
    ASSERT_TRUE(p);
    EXPECT_LT(p->xUm, inside(l, 0.9, 0.9).xUm - 10);
}

TEST_P(StageConformance, ZeroTimeoutOnARealMoveIsATimeout) {
    auto s = GetParam().make(true);
    auto r = s->moveTo(inside(s->limits(), 0.5, 0.5), 0ms);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout) << r.error().message;
}

INSTANTIATE_TEST_SUITE_P(AllModels, StageConformance, ::testing::ValuesIn(stageModels()),
                         [](const auto& i) { return i.param.name; });

} // namespace slicestation::test
