// The stage models the conformance suite runs against.
#include "stage_conformance.hpp"

#include "slicestation/sim/faulty_stage.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include <cassert>

namespace slicestation::test {

namespace {
std::unique_ptr<sim::SimStage> makeSim(bool slow) {
    sim::SimStageConfig cfg;
    if (slow) { // real time, slow enough that a long move is still running when stop() comes
        cfg.clock = std::make_shared<core::SteadyClock>();
        cfg.speedUmPerS = 2'000;
    } else {
        cfg.clock = std::make_shared<core::VirtualClock>();
    }
    auto s = sim::SimStage::create(cfg);
    assert(s);
    return std::move(s).value();
}
} // namespace

std::vector<StageModel> simStageModels() {
    return {
        {"SimStage", [](bool slow) -> std::unique_ptr<hw::Stage> { return makeSim(slow); }},
        {"FaultyStageWithoutFaults",
         [](bool slow) -> std::unique_ptr<hw::Stage> {
             std::shared_ptr<core::Clock> clock = std::make_shared<core::VirtualClock>();
             auto f = sim::FaultyStage::create(makeSim(slow), clock);
             assert(f);
             return std::move(f).value();
         }},
    };
}

} // namespace slicestation::test
