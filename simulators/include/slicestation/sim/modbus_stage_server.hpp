#pragma once
/// stage-sim: a Modbus server (libmodbus) that behaves like the stage drives of the shipped
/// presets, one slave per axis, with motion that takes time (sim::SimAxis on the steady clock).
///
/// It implements each vendor's registers independently of the driver's register maps (from
/// the vendors' documentation), so driver tests check the maps against the protocol.
/// Transports: TCP on 127.0.0.1 (port 0 = any free port) and RTU on a pseudo-terminal whose
/// slave path rtuDevice() a client opens. Reply faults (dropped, bad CRC / corrupt header,
/// exception "busy", slow) and axis faults (stall, alarm mid-move, feedback drift) are injected
/// at run time. Threading: one server thread; every public call is thread-safe.

#include "slicestation/core/result.hpp"
#include "slicestation/sim/sim_axis.hpp"

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::sim {

enum class StageProtocol { OrientalAz, LeadshinePr, AppliedMotionQ };

/// "oriental-az", "leadshine-pr", "applied-motion-q"; NotFound otherwise.
core::Result<StageProtocol> stageProtocolFromName(const std::string& name);

struct StageServerConfig {
    StageProtocol protocol = StageProtocol::OrientalAz;
    std::vector<int> slaves{1, 2, 3};
    bool tcp = true; ///< else RTU on a new pseudo-terminal
    int tcpPort = 0; ///< 0: any free port (see tcpPort())
};

enum class ReplyFault {
    Drop,      ///< no reply at all (the client times out)
    Corrupt,   ///< RTU: bad CRC; TCP: corrupt MBAP header
    Exception, ///< exception 06 "slave device busy"
    Slow,      ///< reply after slowDelay
    Truncated, ///< only the first part of the reply frame, the rest never comes
};

class ModbusStageServer {
public:
    /// Binds / opens the transport and starts the server thread. IoError with errno on failure.
    static core::Result<std::unique_ptr<ModbusStageServer>> create(StageServerConfig config);
    ~ModbusStageServer();

    int tcpPort() const;
    std::string rtuDevice() const;

    /// The next `count` replies (any slave) get `fault`; count < 0: all until cleared.
    void injectReplyFault(ReplyFault fault, int count, std::chrono::milliseconds slowDelay = {});
    void clearReplyFaults();
    void setStall(int slave, bool stall);
    void armAlarm(int slave, std::uint32_t code);
    void setDriftSteps(int slave, double steps);

    AxisState axisState(int slave) const;
    std::uint64_t requestCount() const;
    std::uint64_t writeCount() const; ///< FC05/06/15/16 requests received

    void stop() noexcept;

    struct Impl;

private:
    explicit ModbusStageServer(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
};

} // namespace slicestation::sim
