// stage-sim: serve a simulated Modbus stage (TCP on 127.0.0.1 or RTU on a pseudo-terminal).
#include "slicestation/sim/modbus_stage_server.hpp"

#include <CLI/CLI.hpp>

#include <csignal>
#include <iostream>

int main(int argc, char** argv) {
    using namespace slicestation::sim;
    CLI::App app{"stage-sim: a simulated Modbus XY(Z) stage speaking a real drive protocol"};
    std::string preset = "oriental-az";
    bool rtu = false;
    int port = 5020;
    std::vector<int> slaves{1, 2, 3};
    int stallSlave = 0, alarmSlave = 0, driftSlave = 0;
    double driftSteps = 50;
    int drop = 0, badCrc = 0, exceptions = 0, slowMs = 0;
    app.add_option("--preset", preset, "oriental-az, leadshine-pr or applied-motion-q");
    app.add_flag("--rtu", rtu, "Serve RTU on a new pseudo-terminal instead of TCP");
    app.add_option("--port", port, "TCP port on 127.0.0.1 (0: any free port)");
    app.add_option("--slaves", slaves, "Slave ids, one per axis")->delimiter(',');
    app.add_option("--stall-slave", stallSlave, "This axis never gets in position");
    app.add_option("--alarm-slave", alarmSlave, "This axis raises alarm 0x30 in its next move");
    app.add_option("--drift-slave", driftSlave, "This axis' feedback drifts from the command");
    app.add_option("--drift-steps", driftSteps, "Drift of --drift-slave, steps");
    app.add_option("--drop-replies", drop, "Drop the next N replies (-1: all)");
    app.add_option("--bad-crc", badCrc, "Corrupt the next N replies (-1: all)");
    app.add_option("--exception-replies", exceptions, "Answer the next N requests with 'busy'");
    app.add_option("--slow-ms", slowMs, "Delay every reply by this many ms");
    CLI11_PARSE(app, argc, argv);

    auto protocol = stageProtocolFromName(preset);
    if (!protocol) {
        std::cerr << "stage-sim: error: " << protocol.error().message << "\n";
        return 2;
    }
    // Block the signals before the server thread starts so only sigwait sees them.
    sigset_t set;
    sigemptyset(&set);
    sigaddset(&set, SIGINT);
    sigaddset(&set, SIGTERM);
    pthread_sigmask(SIG_BLOCK, &set, nullptr);

    StageServerConfig cfg;
    cfg.protocol = *protocol;
    cfg.slaves = slaves;
    cfg.tcp = !rtu;
    cfg.tcpPort = port;
    auto server = ModbusStageServer::create(cfg);
    if (!server) {
        std::cerr << "stage-sim: error: " << server.error().message << "\n";
        return 1;
    }
    auto& s = **server;
    if (stallSlave)
        s.setStall(stallSlave, true);
    if (alarmSlave)
        s.armAlarm(alarmSlave, 0x30);
    if (driftSlave)
        s.setDriftSteps(driftSlave, driftSteps);
    if (drop)
        s.injectReplyFault(ReplyFault::Drop, drop);
    if (badCrc)
        s.injectReplyFault(ReplyFault::Corrupt, badCrc);
    if (exceptions)
        s.injectReplyFault(ReplyFault::Exception, exceptions);
    if (slowMs)
        s.injectReplyFault(ReplyFault::Slow, -1, std::chrono::milliseconds(slowMs));
    std::cout << "stage-sim: SIMULATED stage, protocol " << preset << ", slaves";
    for (int id : slaves)
        std::cout << " " << id;
    if (rtu)
        std::cout << "\nstage-sim: rtu device " << s.rtuDevice() << "\n";
    else
        std::cout << "\nstage-sim: tcp 127.0.0.1:" << s.tcpPort() << "\n";
    std::cout.flush();
    int sig = 0;
    sigwait(&set, &sig);
    s.stop();
    return 0;
}
