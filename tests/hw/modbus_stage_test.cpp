// The Modbus stage driver against stage-sim, for every preset, over TCP and RTU (pty), and for
// every injected fault. Each error code the driver returns is provoked here or in conformance.
#include "modbus_fixture.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <thread>
#include <tuple>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;
using sim::ReplyFault;

struct Case {
    std::string preset;
    bool tcp;
};

class ModbusStageProtocol : public ::testing::TestWithParam<Case> {
protected:
    void SetUp() override {
        rig_ = makeRig(GetParam().preset, GetParam().tcp);
        ASSERT_TRUE(rig_.stage);
    }
    drivers::ModbusStage& stage() { return *rig_.stage; }
    sim::ModbusStageServer& server() { return *rig_.server; }
    ModbusRig rig_;
};

TEST_P(ModbusStageProtocol, MoveReachesTargetOnTheDrives) {
    auto r = stage().moveTo({1000, 500, 250}, 5s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_NEAR(r->xUm, 1000, 1);
    EXPECT_NEAR(server().axisState(1).feedbackSteps, 2000, 1); // 2 steps/um
    EXPECT_NEAR(server().axisState(2).feedbackSteps, 1000, 1);
    EXPECT_NEAR(server().axisState(3).feedbackSteps, 500, 1);
    auto p = stage().position(1s);
    ASSERT_TRUE(p);
    EXPECT_NEAR(p->yUm, 500, 1);
}

TEST_P(ModbusStageProtocol, HomeRunsTheDriveHoming) {
    ASSERT_TRUE(stage().moveTo({800, 300, 100}, 5s));
    auto r = stage().home(5s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_NEAR(r->xUm, 0, 1);
    EXPECT_TRUE(server().axisState(1).homeEnd);
}

TEST_P(ModbusStageProtocol, SoftLimitRefusalSendsNothing) {
    const auto before = server().requestCount();
    auto r = stage().moveTo({75'001, 0, 0}, 5s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::OutOfRange);
    EXPECT_EQ(server().requestCount(), before);
}

TEST_P(ModbusStageProtocol, StallTimesOutAndStopsTheDrives) {
    server().setStall(2, true);
    auto r = stage().moveTo({1000, 1000, 0}, 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout) << r.error().message;
    EXPECT_FALSE(server().axisState(2).moving) << "stop was not sent after the timeout";
}

TEST_P(ModbusStageProtocol, AlarmMidMoveIsReadAndResetOnlyWhenAsked) {
    server().armAlarm(1, 0x30);
    auto r = stage().moveTo({2000, 0, 0}, 5s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Alarm);
    EXPECT_NE(r.error().message.find("0x0030"), std::string::npos) << r.error().message;
    auto a = stage().alarm(1s);
    ASSERT_TRUE(a) << a.error().message;
    EXPECT_TRUE(a->active);
    EXPECT_EQ(a->code, 0x30u);
    EXPECT_EQ(a->axis, "x");
    EXPECT_EQ(server().axisState(1).alarmCode, 0x30u) << "the driver reset the alarm by itself";
    ASSERT_TRUE(stage().resetAlarm(1s));
    EXPECT_EQ(server().axisState(1).alarmCode, 0u);
    EXPECT_FALSE(stage().alarm(1s)->active);
    EXPECT_TRUE(stage().moveTo({100, 0, 0}, 5s));
}

TEST_P(ModbusStageProtocol, OneDroppedReplyIsRetried) {
    server().injectReplyFault(ReplyFault::Drop, 1);
    auto r = stage().position(2s);
    EXPECT_TRUE(r) << r.error().message;
}

TEST_P(ModbusStageProtocol, NoRepliesIsATimeout) {
    server().injectReplyFault(ReplyFault::Drop, -1);
    auto r = stage().position(2s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout) << r.error().message;
    EXPECT_NE(r.error().message.find("slave 1"), std::string::npos) << r.error().message;
}

TEST_P(ModbusStageProtocol, OneCorruptReplyIsRetried) {
    server().injectReplyFault(ReplyFault::Corrupt, 1);
    auto r = stage().moveTo({300, 300, 0}, 5s);
    EXPECT_TRUE(r) << r.error().message;
}

TEST_P(ModbusStageProtocol, PersistentCorruptionIsAnIoError) {
    server().injectReplyFault(ReplyFault::Corrupt, -1);
    auto r = stage().position(2s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError) << r.error().message;
}

TEST_P(ModbusStageProtocol, BusyExceptionIsRetried) {
    server().injectReplyFault(ReplyFault::Exception, 2);
    auto r = stage().alarm(2s);
    EXPECT_TRUE(r) << r.error().message;
}

TEST_P(ModbusStageProtocol, PersistentExceptionIsAnIoError) {
    server().injectReplyFault(ReplyFault::Exception, -1);
    auto r = stage().moveTo({10, 10, 0}, 2s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::IoError);
    EXPECT_NE(r.error().message.find("busy"), std::string::npos) << r.error().message;
}

// Found by fuzz_modbus: libmodbus waits its own byte timeout (0.5 s) for the rest of a frame, so
// a truncated reply held each attempt that long, whatever the caller's deadline.
TEST_P(ModbusStageProtocol, ATruncatedReplyDoesNotHoldTheDriverPastItsDeadline) {
    server().injectReplyFault(ReplyFault::Truncated, -1);
    const auto t0 = std::chrono::steady_clock::now();
    auto r = stage().position(150ms);
    const auto took = std::chrono::steady_clock::now() - t0;
    ASSERT_FALSE(r);
    EXPECT_TRUE(r.error().code == ErrorCode::Timeout || r.error().code == ErrorCode::IoError)
        << r.error().message;
    EXPECT_LT(took, 400ms) << "the 150 ms deadline was overrun";
    server().clearReplyFaults();
    EXPECT_TRUE(stage().position(1s)) << "the driver recovers once the replies are whole again";
}

TEST_P(ModbusStageProtocol, SlowRepliesWithinTheTimeoutWork) {
    server().injectReplyFault(ReplyFault::Slow, -1, 20ms);
    auto r = stage().position(2s);
    EXPECT_TRUE(r) << r.error().message;
}

TEST_P(ModbusStageProtocol, RepliesSlowerThanTheTimeoutAreATimeout) {
    server().injectReplyFault(ReplyFault::Slow, -1, 250ms);
    auto r = stage().position(2s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout) << r.error().message;
}

TEST_P(ModbusStageProtocol, DriftingFeedbackNeverSettles) {
    server().setDriftSteps(1, 40); // 20 um off with a 1 um window
    auto r = stage().moveTo({500, 0, 0}, 1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Timeout);
    EXPECT_NE(r.error().message.find("feedback"), std::string::npos) << r.error().message;
}

TEST_P(ModbusStageProtocol, ServerGoneIsReported) {
    server().stop();
    auto r = stage().position(2s);
    ASSERT_FALSE(r);
    // TCP: connection reset, reconnect refused. RTU: the pty hung up, like an unplugged
    // USB-RS485 adapter.
    EXPECT_EQ(r.error().code, ErrorCode::Disconnected) << r.error().message;
}

INSTANTIATE_TEST_SUITE_P(PresetsAndTransports, ModbusStageProtocol,
                         ::testing::Values(Case{"oriental-az", true}, Case{"oriental-az", false},
                                           Case{"leadshine-pr", true}, Case{"leadshine-pr", false},
                                           Case{"applied-motion-q", true},
                                           Case{"applied-motion-q", false}),
                         [](const auto& i) {
                             std::string n = i.param.preset + (i.param.tcp ? "_tcp" : "_rtu");
                             for (auto& c : n)
                                 if (c == '-')
                                     c = '_';
                             return n;
                         });

TEST(ModbusStage, TcpReconnectsAfterTheConnectionDrops) {
    // A server restarted on the same port: the driver reconnects by itself.
    sim::StageServerConfig sc;
    auto first = sim::ModbusStageServer::create(sc).value();
    const int port = first->tcpPort();
    auto stage =
        drivers::ModbusStage::create(rigConfig("oriental-az", *first, true, false)).value();
    ASSERT_TRUE(stage->position(1s));
    first->stop();
    first.reset();
    EXPECT_FALSE(stage->position(1s));
    sc.tcpPort = port;
    auto second = sim::ModbusStageServer::create(sc);
    ASSERT_TRUE(second) << second.error().message;
    auto p = stage->position(2s);
    EXPECT_TRUE(p) << p.error().message;
}

TEST(ModbusStage, AClientHangingUpBeforeItsRepliesLeavesTheServerServing) {
    // A driver that gives up on slow replies and reconnects leaves the server writing to a
    // closed connection: the first reply draws a reset, the next is an EPIPE for that reply,
    // never a SIGPIPE ending the process that serves (this test, or stage-sim).
    sim::StageServerConfig sc;
    auto server = sim::ModbusStageServer::create(sc).value();
    server->injectReplyFault(ReplyFault::Slow, 2, 150ms);
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    ASSERT_GE(fd, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(static_cast<std::uint16_t>(server->tcpPort()));
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
    // Two reads of holding registers 0..1 of unit 1 (MBAP: transaction 1 and 2, length 6).
    const unsigned char requests[] = {0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 2,
                                      0, 2, 0, 0, 0, 6, 1, 3, 0, 0, 0, 2};
    ASSERT_EQ(::send(fd, requests, sizeof requests, MSG_NOSIGNAL),
              static_cast<ssize_t>(sizeof requests));
    ::close(fd);
    const auto deadline = std::chrono::steady_clock::now() + 3s;
    while (server->requestCount() < 2 && std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(10ms);
    EXPECT_EQ(server->requestCount(), 2u) << "the server took both requests";
    std::this_thread::sleep_for(300ms); // the second slow reply is written (and fails) meanwhile
    auto stage = drivers::ModbusStage::create(rigConfig("oriental-az", *server, true, false));
    ASSERT_TRUE(stage) << stage.error().message;
    auto p = (*stage)->position(1s);
    EXPECT_TRUE(p) << p.error().message;
}

TEST(ModbusStage, AMoveReportsItsFeedbackOnTheWayAtMostFiveTimesASecond) {
    // 2 mm at 2 mm/s: about a second on the way, read from the drives' feedback registers.
    ModbusRig rig = makeRig("oriental-az", true, /*slow=*/true);
    ASSERT_TRUE(rig.stage);
    std::vector<std::pair<double, std::chrono::steady_clock::time_point>> seen;
    rig.stage->setMoveObserver(
        [&](const hw::StagePosition& p, auto at) { seen.emplace_back(p.xUm, at); });
    auto r = rig.stage->moveTo({2000, 0, 0}, 10s);
    ASSERT_TRUE(r) << r.error().message;
    ASSERT_GE(seen.size(), 3u); // positions on the way, not only the end
    EXPECT_LE(seen.size(), 7u); // at most every 200 ms over about 1 s
    for (size_t i = 1; i < seen.size(); ++i) {
        EXPECT_GE(seen[i].first, seen[i - 1].first); // along the move, in order
        EXPECT_GE(seen[i].second - seen[i - 1].second, 190ms);
    }
    // The first read may come before the drive starts; later ones lie on the way.
    const auto onTheWay = std::count_if(
        seen.begin(), seen.end(), [](const auto& s) { return s.first > 1.0 && s.first < 1999.0; });
    EXPECT_GE(onTheWay, 2);
    // Without an observer nothing extra is read.
    rig.stage->setMoveObserver({});
    ASSERT_TRUE(rig.stage->moveTo({0, 0, 0}, 10s));
}

TEST(ModbusStage, ConnectionRefusedIsDisconnected) {
    sim::StageServerConfig sc;
    auto server = sim::ModbusStageServer::create(sc).value();
    auto cfg = rigConfig("oriental-az", *server, true, false);
    server.reset(); // the port is free now
    auto r = drivers::ModbusStage::create(cfg);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Disconnected) << r.error().message;
}

TEST(ModbusStage, MissingSerialDeviceIsNotFound) {
    drivers::ModbusStageConfig cfg;
    cfg.transport = drivers::ModbusStageConfig::Transport::Rtu;
    cfg.device = "/dev/serial/by-id/no-such-adapter";
    cfg.map = drivers::presetMap("oriental-az").value();
    cfg.axes = {{"x", 1, 1, 0, 10}, {"y", 2, 1, 0, 10}};
    auto r = drivers::ModbusStage::create(cfg);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::NotFound) << r.error().message;
}

TEST(ModbusStage, BadConfigNamesTheKey) {
    drivers::ModbusStageConfig cfg;
    cfg.map = drivers::presetMap("oriental-az").value();
    cfg.axes = {{"x", 0, 1, 0, 10}, {"y", 2, 1, 0, 10}};
    auto r = drivers::ModbusStage::create(cfg);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(r.error().message.find("stage.axes.x.slave"), std::string::npos) << r.error().message;
    cfg.axes = {{"x", 1, 1, 0, 10}};
    EXPECT_NE(drivers::ModbusStage::create(cfg).error().message.find("y axis"), std::string::npos);
}

TEST(ModbusStage, MapWithoutHomeIsUnsupported) {
    sim::StageServerConfig sc;
    auto server = sim::ModbusStageServer::create(sc).value();
    auto cfg = rigConfig("oriental-az", *server, true, false);
    cfg.map.home.clear();
    auto stage = drivers::ModbusStage::create(cfg).value();
    auto r = stage->home(1s);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::Unsupported);
}

TEST(RegisterMap, PresetsParseAndUnknownIsNotFound) {
    for (const auto& name : drivers::presetNames()) {
        auto m = drivers::presetMap(name);
        ASSERT_TRUE(m) << m.error().message;
        EXPECT_FALSE(m->moveAbs.empty());
    }
    auto az = drivers::presetMap("oriental-az").value();
    EXPECT_EQ(az.moveAbs[0].address, 0x0058);
    EXPECT_EQ(az.moveAbs[0].values.size(), 8u);
    EXPECT_EQ(az.positionAddress, 0x00CC);
    auto r = drivers::presetMap("zaber");
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::NotFound);
    EXPECT_NE(r.error().message.find("oriental-az"), std::string::npos);
}

TEST(RegisterMap, MapFileErrorsNameTheKey) {
    auto r = drivers::parseRegisterMap("move_abs = []\n", "my.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("'move_abs'"), std::string::npos) << r.error().message;
    auto text = drivers::presetToml("oriental-az").value();
    auto bad = text;
    bad.replace(bad.find("\"{pos}\""), 7, "\"{where}\"");
    r = drivers::parseRegisterMap(bad, "my.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("move_abs[0].values[2]"), std::string::npos)
        << r.error().message;
    r = drivers::parseRegisterMap("name = [", "broken.toml");
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, ErrorCode::InvalidArgument);
    EXPECT_EQ(drivers::loadRegisterMap("/nonexistent/map.toml").error().code, ErrorCode::NotFound);
}

// A value the drive's register cannot hold is refused, never clipped or wrapped: before, a
// 16-bit speed was clipped to 65535 and a 32-bit one wrapped to whatever its low 32 bits said.
TEST(RegisterMap, LiteralsThatDoNotFitTheirRegisterAreRefused) {
    const auto text = drivers::presetToml("leadshine-pr").value();
    auto bad16 = text;
    bad16.replace(bad16.find("value = 0x0001"), 14, "value = 70000");
    auto r = drivers::parseRegisterMap(bad16, "my.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("move_abs[0].value"), std::string::npos) << r.error().message;
    EXPECT_NE(r.error().message.find("16-bit"), std::string::npos) << r.error().message;
    auto az = drivers::presetToml("oriental-az").value();
    az.replace(az.find("1000, 1]"), 8, "5000000000, 1]");
    r = drivers::parseRegisterMap(az, "my.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("move_abs[0].values[6]"), std::string::npos)
        << r.error().message;
    auto neg = drivers::presetToml("leadshine-pr").value();
    neg.replace(neg.find("value = 0x0001"), 14, "value = -1");
    EXPECT_FALSE(drivers::parseRegisterMap(neg, "my.toml"));
}

TEST(ModbusStage, AMoveWhoseSpeedDoesNotFitTheDriveRegisterSendsNothing) {
    for (const char* preset : {"oriental-az", "leadshine-pr"}) {
        SCOPED_TRACE(preset);
        sim::StageServerConfig sc;
        sc.protocol = sim::stageProtocolFromName(preset).value();
        auto server = sim::ModbusStageServer::create(sc).value();
        auto cfg = rigConfig(preset, *server, true, false);
        cfg.map.speedScale = 1e6; // 1e5 steps/s become 1e11 drive units: more than 32 bits hold
        auto stage = drivers::ModbusStage::create(cfg).value();
        const auto before = server->requestCount();
        auto r = stage->moveTo({1000, 500, 250}, 5s);
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, ErrorCode::OutOfRange);
        EXPECT_NE(r.error().message.find("speed"), std::string::npos) << r.error().message;
        EXPECT_EQ(server->requestCount(), before) << "nothing sent, not even to the first axis";
        EXPECT_EQ(server->axisState(1).feedbackSteps, 0);
    }
}

TEST(RegisterMap, MapFileDrivesTheSimulator) {
    // A custom map file equal to the AZ preset but with the words of 32-bit values spelled out
    // as two 16-bit writes would not be atomic; the file format keeps write32 instead.
    const auto dir = std::filesystem::path(SLST_BINARY_DIR) / "tests_hw_tmp";
    std::filesystem::create_directories(dir);
    const auto file = dir / "custom_az.toml";
    std::ofstream(file) << drivers::presetToml("oriental-az").value();
    auto map = drivers::loadRegisterMap(file);
    ASSERT_TRUE(map) << map.error().message;
    sim::StageServerConfig sc;
    auto server = sim::ModbusStageServer::create(sc).value();
    auto cfg = rigConfig("oriental-az", *server, true, false);
    cfg.map = *map;
    auto stage = drivers::ModbusStage::create(cfg).value();
    EXPECT_TRUE(stage->moveTo({10, 20, 30}, 5s));
}

} // namespace
} // namespace slicestation::test
