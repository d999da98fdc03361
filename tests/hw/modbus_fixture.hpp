#pragma once
// A ModbusStage connected to an in-process stage-sim server.
#include "slicestation/drivers/modbus_stage.hpp"
#include "slicestation/sim/modbus_stage_server.hpp"

#include <gtest/gtest.h>

#include <memory>
#include <string>

namespace slicestation::test {

struct ModbusRig {
    std::unique_ptr<sim::ModbusStageServer> server;
    std::unique_ptr<drivers::ModbusStage> stage;
};

inline drivers::ModbusStageConfig rigConfig(const std::string& preset,
                                            const sim::ModbusStageServer& s, bool tcp, bool slow) {
    drivers::ModbusStageConfig cfg;
    if (tcp) {
        cfg.transport = drivers::ModbusStageConfig::Transport::Tcp;
        cfg.port = s.tcpPort();
    } else {
        cfg.transport = drivers::ModbusStageConfig::Transport::Rtu;
        cfg.device = s.rtuDevice();
    }
    cfg.map = drivers::presetMap(preset).value();
    cfg.axes = {{"x", 1, 2.0, 0, 75'000}, {"y", 2, 2.0, 0, 25'000}, {"z", 3, 2.0, 0, 5'000}};
    cfg.speedUmPerS = slow ? 2'000 : 50'000;
    cfg.accelUmPerS2 = 500'000;
    cfg.positionWindowUm = 1.0;
    cfg.settle = std::chrono::milliseconds(20);
    cfg.pollInterval = std::chrono::milliseconds(5);
    cfg.responseTimeout = std::chrono::milliseconds(100);
    cfg.retries = 2;
    return cfg;
}

inline ModbusRig makeRig(const std::string& preset, bool tcp, bool slow = false) {
    ModbusRig rig;
    sim::StageServerConfig sc;
    sc.protocol = sim::stageProtocolFromName(preset).value();
    sc.tcp = tcp;
    auto server = sim::ModbusStageServer::create(sc);
    EXPECT_TRUE(server) << (server ? "" : server.error().message);
    if (!server)
        return rig;
    rig.server = std::move(server).value();
    auto stage = drivers::ModbusStage::create(rigConfig(preset, *rig.server, tcp, slow));
    EXPECT_TRUE(stage) << (stage ? "" : stage.error().message);
    if (stage)
        rig.stage = std::move(stage).value();
    return rig;
}

} // namespace slicestation::test
