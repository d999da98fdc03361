// Modbus stage models for the conformance suite: the real driver against stage-sim.
#include "modbus_fixture.hpp"
#include "stage_conformance.hpp"

namespace slicestation::test {

namespace {
// The stage owns its server so the conformance suite sees a plain hw::Stage.
class RiggedStage final : public hw::Stage {
public:
    explicit RiggedStage(ModbusRig rig) : rig_(std::move(rig)) {}
    hw::StageLimits limits() const override { return rig_.stage->limits(); }
    core::Result<hw::StagePosition> position(std::chrono::milliseconds t) override {
        return rig_.stage->position(t);
    }
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& p,
                                           std::chrono::milliseconds t) override {
        return rig_.stage->moveTo(p, t);
    }
    core::Result<hw::StagePosition> home(std::chrono::milliseconds t) override {
        return rig_.stage->home(t);
    }
    void stop() noexcept override { rig_.stage->stop(); }
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds t) override {
        return rig_.stage->alarm(t);
    }
    core::Result<void> resetAlarm(std::chrono::milliseconds t) override {
        return rig_.stage->resetAlarm(t);
    }

private:
    ModbusRig rig_;
};

StageModel modbusModel(const std::string& name, const std::string& preset, bool tcp) {
    return {name, [preset, tcp](bool slow) -> std::unique_ptr<hw::Stage> {
                auto rig = makeRig(preset, tcp, slow);
                if (!rig.stage)
                    return nullptr;
                return std::make_unique<RiggedStage>(std::move(rig));
            }};
}
} // namespace

std::vector<StageModel> modbusStageModels() {
    return {modbusModel("ModbusOrientalAzTcp", "oriental-az", true),
            modbusModel("ModbusOrientalAzRtu", "oriental-az", false),
            modbusModel("ModbusLeadshinePrTcp", "leadshine-pr", true),
            modbusModel("ModbusAppliedMotionQTcp", "applied-motion-q", true)};
}

} // namespace slicestation::test
