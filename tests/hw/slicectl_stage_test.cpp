// slicectl stage commands against stage-sim (in this process) and the simulated stage.
#include "../common/run_command.hpp"
#include "slicestation/daemon/config/station_config.hpp"
#include "slicestation/sim/modbus_stage_server.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>

namespace slicestation::test {
namespace {

using core::ErrorCode;

using testing_cli::slicectl;

nlohmann::json lastJson(const std::string& out) {
    const auto pos = out.find('{');
    return nlohmann::json::parse(out.substr(pos == std::string::npos ? 0 : pos), nullptr, false);
}

std::filesystem::path writeConfig(const std::string& name, const std::string& text) {
    const auto dir = std::filesystem::path(SLST_BINARY_DIR) / "tests_hw_tmp";
    std::filesystem::create_directories(dir);
    const auto f = dir / name;
    std::ofstream(f) << text;
    return f;
}

std::string modbusToml(int port, const std::string& preset) {
    return "[stage]\ndriver = \"modbus\"\ntransport = \"tcp\"\nhost = \"127.0.0.1\"\nport = " +
           std::to_string(port) + "\npreset = \"" + preset +
           "\"\nmove_timeout_s = 10\nspeed_um_per_s = 50000\naccel_um_per_s2 = 500000\n"
           "settle_ms = 20\nresponse_timeout_ms = 200\n"
           "[stage.axes.x]\nslave = 1\nsteps_per_um = 2.0\nmin_um = 0\nmax_um = 75000\n"
           "[stage.axes.y]\nslave = 2\nsteps_per_um = 2.0\nmin_um = 0\nmax_um = 25000\n"
           "[stage.axes.z]\nslave = 3\nsteps_per_um = 2.0\nmin_um = 0\nmax_um = 5000\n";
}

class SlicectlStage : public ::testing::Test {
protected:
    void SetUp() override {
        server_ = sim::ModbusStageServer::create({}).value();
        config_ = writeConfig("station_" + std::to_string(server_->tcpPort()) + ".toml",
                              modbusToml(server_->tcpPort(), "oriental-az"));
    }
    std::string stage(const std::string& rest) {
        return "stage --config " + config_.string() + " " + rest;
    }
    std::unique_ptr<sim::ModbusStageServer> server_;
    std::filesystem::path config_;
};

TEST_F(SlicectlStage, MoveThenPosition) {
    auto r = slicectl(stage("move --x-um 1200 --y-um 800 --z-um 100"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    auto j = lastJson(r.output);
    EXPECT_NEAR(j["position"]["x_um"].get<double>(), 1200, 1);
    EXPECT_NEAR(server_->axisState(1).feedbackSteps, 2400, 1);
    r = slicectl(stage("position"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_NEAR(lastJson(r.output)["position"]["y_um"].get<double>(), 800, 1);
    r = slicectl(stage("move --x-um 10 --y-um 20")); // z stays
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_NEAR(lastJson(r.output)["position"]["z_um"].get<double>(), 100, 1);
}

TEST_F(SlicectlStage, MoveOutsideSoftLimitsSendsNothing) {
    const auto before = server_->requestCount();
    auto r = slicectl(stage("move --x-um 80000 --y-um 10"));
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("soft limits"), std::string::npos) << r.output;
    r = slicectl(stage("move --x-um 10 --y-um 10 --z-um -5"));
    EXPECT_NE(r.exitCode, 0);
    EXPECT_EQ(server_->requestCount(), before) << "a refused move reached the drives";
}

TEST_F(SlicectlStage, HomeStopAndResetAlarm) {
    ASSERT_EQ(slicectl(stage("move --x-um 500 --y-um 500")).exitCode, 0);
    auto r = slicectl(stage("home"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_TRUE(lastJson(r.output)["homed"].get<bool>());
    r = slicectl(stage("stop"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    server_->armAlarm(2, 0x30);
    r = slicectl(stage("move --x-um 500 --y-um 500"));
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("alarm"), std::string::npos) << r.output;
    r = slicectl(stage("reset-alarm"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    auto j = lastJson(r.output);
    EXPECT_TRUE(j["alarm_before"]["active"].get<bool>());
    EXPECT_EQ(j["alarm_before"]["code"].get<int>(), 0x30);
    EXPECT_FALSE(j["alarm_after"]["active"].get<bool>());
}

TEST(SlicectlStageConfig, SimulationIsAnnounced) {
    const auto f = writeConfig(
        "station_sim.toml", "[stage]\ndriver = \"sim\"\n[stage.axes.x]\nmin_um = 0\nmax_um = 1000\n"
                            "[stage.axes.y]\nmin_um = 0\nmax_um = 1000\n");
    auto r = slicectl("stage --config " + f.string() + " move --x-um 100 --y-um 200");
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_NE(r.output.find("SIMULATED"), std::string::npos) << r.output;
    EXPECT_TRUE(lastJson(r.output)["simulated"].get<bool>());
}

TEST(SlicectlStageConfig, ConfigErrorsNameTheKey) {
    auto text = modbusToml(5020, "oriental-az");
    text.replace(text.find("slave = 2"), 9, "slave = 0");
    const auto f = writeConfig("station_bad.toml", text);
    auto r = slicectl("stage --config " + f.string() + " position");
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("stage.axes.y.slave"), std::string::npos) << r.output;

    auto c = daemon::parseStationConfig(modbusToml(5020, "nope"), "s.toml");
    ASSERT_FALSE(c);
    EXPECT_NE(c.error().message.find("stage.preset"), std::string::npos) << c.error().message;
    c = daemon::parseStationConfig("[stage]\ndriver = \"modbus\"\n", "s.toml");
    ASSERT_FALSE(c);
    EXPECT_NE(c.error().message.find("stage.axes"), std::string::npos) << c.error().message;
    c = daemon::parseStationConfig("[stage]\ndriver = \"usb\"\n", "s.toml");
    ASSERT_FALSE(c);
    EXPECT_NE(c.error().message.find("stage.driver"), std::string::npos);
    text = modbusToml(5020, "oriental-az");
    text.replace(text.find("transport = \"tcp\""), 17, "transport = \"rtu\"");
    c = daemon::parseStationConfig(text, "s.toml");
    ASSERT_FALSE(c);
    // The tcp keys left in an rtu file are refused by name (issue 20: no key silently ignored).
    EXPECT_NE(c.error().message.find("stage.host: only for transport = \"tcp\""), std::string::npos)
        << c.error().message;
}

TEST(SlicectlStageConfig, NoStageRunningIsAClearError) {
    sim::StageServerConfig sc;
    int port;
    {
        auto s = sim::ModbusStageServer::create(sc).value();
        port = s->tcpPort();
    }
    const auto f = writeConfig("station_nothing.toml", modbusToml(port, "leadshine-pr"));
    auto r = slicectl("stage --config " + f.string() + " position");
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("cannot connect"), std::string::npos) << r.output;
}

} // namespace
} // namespace slicestation::test
