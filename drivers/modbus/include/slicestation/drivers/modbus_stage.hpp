#pragma once
/// An XY(Z) stage whose axes are Modbus drives (one slave per axis, one bus), RTU or TCP,
/// through libmodbus. The register map is data (register_map.hpp).
///
/// Contract (hw::Stage): soft limits are checked before anything is sent; a move is settled
/// when every drive says in position and not moving, the feedback is within the position
/// window, and both held for the settle time; a wait that times out sends stop and returns
/// Timeout. Each request has the response timeout; failed requests (timeout, bad CRC,
/// exception "busy") are retried `retries` times after a flush; a lost TCP connection is
/// re-established. Alarms are read and reported (Alarm), reset only by resetAlarm().
/// Threading: one owning thread; stop() from any thread (it takes the bus between requests).

#include "slicestation/core/stage.hpp"
#include "slicestation/drivers/register_map.hpp"

#include <chrono>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::drivers {

struct ModbusAxisConfig {
    std::string name; ///< "x", "y" or "z"
    int slave = 1;    ///< 1..247
    double stepsPerUm = 1.0;
    double minUm = 0;
    double maxUm = 0;
};

struct ModbusStageConfig {
    enum class Transport { Tcp, Rtu };
    Transport transport = Transport::Tcp;
    std::string host = "127.0.0.1";
    int port = 502;
    std::string device; ///< RTU: serial device (prefer /dev/serial/by-id/...)
    int baud = 115200;
    char parity = 'E'; ///< 'N', 'E' or 'O'
    int dataBits = 8;
    int stopBits = 1;
    RegisterMap map;
    std::vector<ModbusAxisConfig> axes; ///< x and y required, z optional
    double speedUmPerS = 10'000;
    double accelUmPerS2 = 50'000;
    double positionWindowUm = 1.0;
    std::chrono::milliseconds settle{50};
    std::chrono::milliseconds pollInterval{10};
    std::chrono::milliseconds responseTimeout{200};
    int retries = 2; ///< extra attempts per request after a failure
};

class ModbusStage final : public hw::Stage {
public:
    /// Validates the configuration (InvalidArgument naming the field), opens the bus:
    /// NotFound (no such serial device), Disconnected (TCP connection refused), IoError.
    static core::Result<std::unique_ptr<ModbusStage>> create(ModbusStageConfig config);
    ~ModbusStage() override;

    /// Reads the feedback position at most every 200 ms while a move or homing is under way
    /// (one read per axis, between status polls) and reports it.
    void setMoveObserver(hw::MoveObserver observer) override;
    hw::StageLimits limits() const override;
    core::Result<hw::StagePosition> position(std::chrono::milliseconds timeout) override;
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& target,
                                           std::chrono::milliseconds timeout) override;
    core::Result<hw::StagePosition> home(std::chrono::milliseconds timeout) override;
    void stop() noexcept override;
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds timeout) override;
    core::Result<void> resetAlarm(std::chrono::milliseconds timeout) override;

    struct Impl;

private:
    explicit ModbusStage(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
};

} // namespace slicestation::drivers
