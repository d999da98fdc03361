#include "slicestation/drivers/modbus_stage.hpp"

#include "slicestation/core/clock.hpp"

#include <modbus/modbus.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <sstream>

namespace slicestation::drivers {

using core::ErrorCode;
using core::makeError;
using Clock = std::chrono::steady_clock;

namespace {

struct ModbusDeleter {
    void operator()(modbus_t* ctx) const noexcept {
        modbus_close(ctx);
        modbus_free(ctx);
    }
};
using ModbusPtr = std::unique_ptr<modbus_t, ModbusDeleter>;

std::string hex(unsigned v) {
    char buf[16];
    std::snprintf(buf, sizeof buf, "0x%04X", v);
    return buf;
}

enum class Failure { Timeout, Corrupt, Busy, Exception, Connection, Other };

Failure classify(int e) {
    switch (e) {
    case ETIMEDOUT:
        return Failure::Timeout;
    case EMBBADCRC:
    case EMBBADDATA:
    case EMBMDATA:
    case EMBBADSLAVE:
    case EMBBADEXC:
    case EMBUNKEXC:
        return Failure::Corrupt;
    case EMBXSBUSY:
    case EMBXACK:
    case EMBXGTAR:
        return Failure::Busy;
    case EMBXILFUN:
    case EMBXILADD:
    case EMBXILVAL:
    case EMBXSFAIL:
    case EMBXMEMPAR:
    case EMBXGPATH:
        return Failure::Exception;
    case ECONNRESET:
    case ECONNREFUSED:
    case EPIPE:
    case ENOTCONN:
    case EBADF:
    case EIO:
        return Failure::Connection;
    default:
        return Failure::Other;
    }
}

} // namespace

struct AxisStatus {
    bool alarm = false, done = false;
};

struct ModbusStage::Impl {
    ModbusStageConfig cfg;
    ModbusPtr ctx;
    std::mutex bus; // one request at a time: the owner thread and stop()
    bool connected = false;
    core::StopSignal stopSignal;
    /// Told the feedback position while a move is under way (setMoveObserver), at most every
    /// kObserveEvery: each report costs one position read per axis on the bus.
    hw::MoveObserver observer;
    Clock::time_point lastObserved{};
    static constexpr std::chrono::milliseconds kObserveEvery{200};

    std::string describe() const {
        return cfg.transport == ModbusStageConfig::Transport::Tcp
                   ? "modbus tcp " + cfg.host + ":" + std::to_string(cfg.port)
                   : "modbus rtu " + cfg.device;
    }

    // Runs one request with retries, flush and reconnect. `op` returns libmodbus' rc.
    template <class Op>
    core::Result<void> transact(const ModbusAxisConfig& axis, const std::string& what,
                                Clock::time_point deadline, Op&& op) {
        std::lock_guard lock(bus);
        bool timedOut = false;
        core::Error last{ErrorCode::Timeout, "deadline passed before the request", 0};
        for (int attempt = 0; attempt <= cfg.retries; ++attempt) {
            const auto now = Clock::now();
            if (now >= deadline) {
                timedOut = true;
                break;
            }
            if (!connected) {
                if (modbus_connect(ctx.get()) != 0) {
                    last = makeError(ErrorCode::Disconnected,
                                     "reconnect failed: " + std::string(modbus_strerror(errno)),
                                     errno);
                    continue;
                }
                connected = true;
            }
            const auto remaining = std::chrono::duration_cast<std::chrono::microseconds>(
                std::min<Clock::duration>(cfg.responseTimeout, deadline - now));
            const auto sec = static_cast<std::uint32_t>(remaining.count() / 1'000'000);
            const auto usec = static_cast<std::uint32_t>(remaining.count() % 1'000'000);
            modbus_set_response_timeout(ctx.get(), sec, usec);
            // libmodbus waits up to its byte timeout (0.5 s by default) between the bytes of a
            // reply: a drive that sends a truncated frame held every request that long, past the
            // caller's deadline. The same bound applies to the rest of a frame.
            modbus_set_byte_timeout(ctx.get(), sec, usec);
            modbus_set_slave(ctx.get(), axis.slave);
            errno = 0;
            if (op(ctx.get()) >= 0)
                return {};
            const int e = errno;
            const Failure f = classify(e);
            const std::string why = modbus_strerror(e);
            switch (f) {
            case Failure::Timeout:
                timedOut = true;
                last = makeError(ErrorCode::Timeout, "no reply: " + why, e);
                modbus_flush(ctx.get());
                break;
            case Failure::Corrupt:
            case Failure::Busy:
                last = makeError(ErrorCode::IoError, "bad reply: " + why, e);
                if (f == Failure::Corrupt && cfg.transport == ModbusStageConfig::Transport::Tcp) {
                    // A TCP stream cannot be resynchronised after a bad frame (the rest of it, or
                    // a late reply, would be read as the next header): start a new connection.
                    modbus_close(ctx.get());
                    connected = false;
                } else {
                    modbus_flush(ctx.get());
                }
                break;
            case Failure::Exception:
                return makeError(ErrorCode::IoError,
                                 describe() + " slave " + std::to_string(axis.slave) + " (axis " +
                                     axis.name + ") " + what + ": exception reply: " + why,
                                 e);
            case Failure::Connection:
                last = makeError(ErrorCode::Disconnected, "connection lost: " + why, e);
                modbus_close(ctx.get());
                connected = false;
                break;
            case Failure::Other:
                last = makeError(ErrorCode::IoError, why, e);
                modbus_flush(ctx.get());
                break;
            }
        }
        // A timeout anywhere is the root cause (a late reply then looks corrupt).
        if (timedOut && last.code != ErrorCode::Disconnected)
            last.code = ErrorCode::Timeout;
        last.message = describe() + " slave " + std::to_string(axis.slave) + " (axis " + axis.name +
                       ") " + what + ": " + last.message + " (" + std::to_string(cfg.retries + 1) +
                       " attempts)";
        return last;
    }

    std::vector<std::uint16_t> split32(std::int64_t v) const {
        const auto u = static_cast<std::uint32_t>(static_cast<std::int32_t>(v));
        const auto hi = static_cast<std::uint16_t>(u >> 16),
                   lo = static_cast<std::uint16_t>(u & 0xFFFF);
        return cfg.map.wordOrder == WordOrder::HighFirst ? std::vector<std::uint16_t>{hi, lo}
                                                         : std::vector<std::uint16_t>{lo, hi};
    }
    std::uint32_t join32(const std::uint16_t* r) const {
        return cfg.map.wordOrder == WordOrder::HighFirst ? (std::uint32_t(r[0]) << 16) | r[1]
                                                         : (std::uint32_t(r[1]) << 16) | r[0];
    }

    core::Result<void> write16(const ModbusAxisConfig& a, std::uint16_t addr, std::uint16_t v,
                               Clock::time_point deadline) {
        return transact(a, "write " + hex(addr), deadline,
                        [&](modbus_t* c) { return modbus_write_register(c, addr, v); });
    }
    core::Result<void> writeMany(const ModbusAxisConfig& a, std::uint16_t addr,
                                 const std::vector<std::uint16_t>& regs,
                                 Clock::time_point deadline) {
        return transact(a, "write " + hex(addr) + " x" + std::to_string(regs.size()), deadline,
                        [&](modbus_t* c) {
                            return modbus_write_registers(c, addr, static_cast<int>(regs.size()),
                                                          regs.data());
                        });
    }
    core::Result<std::uint16_t> read16(const ModbusAxisConfig& a, std::uint16_t addr,
                                       Clock::time_point deadline) {
        std::uint16_t r = 0;
        auto rc = transact(a, "read " + hex(addr), deadline,
                           [&](modbus_t* c) { return modbus_read_registers(c, addr, 1, &r); });
        if (!rc)
            return rc.error();
        return r;
    }
    /// Both words in one FC03: a split read could mix two different values.
    core::Result<std::uint32_t> read32(const ModbusAxisConfig& a, std::uint16_t addr,
                                       Clock::time_point deadline) {
        std::uint16_t r[2] = {0, 0};
        auto rc = transact(a, "read " + hex(addr) + " x2", deadline,
                           [&](modbus_t* c) { return modbus_read_registers(c, addr, 2, r); });
        if (!rc)
            return rc.error();
        return join32(r);
    }

    /// The registers each step writes, every value encoded and checked first: a value that does
    /// not fit its register (a speed or position beyond what the drive can hold) is OutOfRange
    /// naming it, and nothing of the sequence is sent, rather than a clipped or wrapped value
    /// reaching the drive.
    core::Result<std::vector<std::vector<std::uint16_t>>>
    encodeSteps(const std::vector<MapStep>& steps, const ModbusAxisConfig& a,
                const MoveQuantities& q) const {
        std::vector<std::vector<std::uint16_t>> out;
        for (const MapStep& s : steps) {
            std::vector<std::uint16_t> regs;
            const bool wide =
                s.kind == MapStep::Kind::Write32 || s.kind == MapStep::Kind::Write32Block;
            if (s.kind == MapStep::Kind::Write16 || wide) {
                for (const MapValue& v : s.values) {
                    auto e = encodeChecked(cfg.map, v, q, wide);
                    if (!e)
                        return makeError(ErrorCode::OutOfRange,
                                         describe() + " slave " + std::to_string(a.slave) +
                                             " (axis " + a.name + ") register " + hex(s.address) +
                                             ": " + e.error().message);
                    if (wide) {
                        auto w = split32(*e);
                        regs.insert(regs.end(), w.begin(), w.end());
                    } else {
                        regs.push_back(static_cast<std::uint16_t>(*e));
                    }
                }
            }
            out.push_back(std::move(regs));
        }
        return out;
    }

    core::Result<void> runSteps(const std::vector<MapStep>& steps, const ModbusAxisConfig& a,
                                const MoveQuantities& q, Clock::time_point deadline) {
        auto encoded = encodeSteps(steps, a, q);
        if (!encoded)
            return encoded.error();
        for (std::size_t i = 0; i < steps.size(); ++i) {
            const MapStep& s = steps[i];
            const auto& regs = (*encoded)[i];
            core::Result<void> r;
            switch (s.kind) {
            case MapStep::Kind::Write16:
                r = write16(a, s.address, regs[0], deadline);
                break;
            case MapStep::Kind::Write32:
            case MapStep::Kind::Write32Block:
                r = writeMany(a, s.address, regs, deadline);
                break;
            case MapStep::Kind::PulseBit:
                r = write16(a, s.address, static_cast<std::uint16_t>(1u << s.bit), deadline);
                if (r)
                    r = write16(a, s.address, 0, deadline);
                break;
            }
            if (!r)
                return r;
        }
        return {};
    }

    static bool bit(std::uint16_t v, int b) { return b >= 0 && ((v >> b) & 1u); }

    core::Result<std::uint32_t> alarmCode(const ModbusAxisConfig& a, Clock::time_point deadline) {
        if (cfg.map.alarm32)
            return read32(a, cfg.map.alarmAddress, deadline);
        auto r = read16(a, cfg.map.alarmAddress, deadline);
        if (!r)
            return r.error();
        return std::uint32_t{*r};
    }

    void sendStopAll(Clock::time_point deadline) noexcept {
        for (const auto& a : cfg.axes)
            (void)runSteps(cfg.map.stop, a, {}, deadline);
    }
    Clock::time_point stopDeadline() const {
        return Clock::now() + cfg.responseTimeout * (cfg.retries + 1) * 2;
    }

    core::Result<hw::StagePosition> readPosition(Clock::time_point deadline) {
        hw::StagePosition p;
        for (const auto& a : cfg.axes) {
            auto s = read32(a, cfg.map.positionAddress, deadline);
            if (!s)
                return s.error();
            const double um = static_cast<std::int32_t>(*s) / a.stepsPerUm;
            (a.name == "x" ? p.xUm : a.name == "y" ? p.yUm : p.zUm) = um;
        }
        return p;
    }

    static double coord(const hw::StagePosition& p, const std::string& axis) {
        return axis == "x" ? p.xUm : axis == "y" ? p.yUm : p.zUm;
    }

    core::Result<hw::StagePosition> waitSettled(const hw::StagePosition* target,
                                                Clock::time_point deadline) {
        Clock::time_point settledSince{};
        bool settling = false;
        std::string reason = "no status read yet";
        for (;;) {
            if (stopSignal.raised())
                return makeError(ErrorCode::Cancelled, describe() + ": stopped");
            bool settled = true;
            for (const auto& a : cfg.axes) {
                auto st = read16(a, cfg.map.status.address, deadline);
                if (!st) {
                    if (st.error().code != ErrorCode::Timeout)
                        sendStopAll(stopDeadline());
                    else if (Clock::now() >= deadline)
                        return timeout(reason);
                    return st.error();
                }
                const auto& b = cfg.map.status;
                if (bit(*st, b.alarm)) {
                    auto code = alarmCode(a, stopDeadline());
                    return makeError(
                        ErrorCode::Alarm,
                        describe() + " slave " + std::to_string(a.slave) + " (axis " + a.name +
                            "): alarm code " +
                            (code ? hex(*code) : "unreadable (" + code.error().message + ")"));
                }
                bool done = !bit(*st, b.moving) && (b.inPosition < 0 || bit(*st, b.inPosition)) &&
                            (b.ready < 0 || bit(*st, b.ready));
                if (!target)
                    done = done && (b.homeEnd < 0 || bit(*st, b.homeEnd)) && !bit(*st, b.homing);
                if (!done) {
                    settled = false;
                    reason = "axis " + a.name + " status " + hex(*st) + " not in position";
                    continue;
                }
                if (target) {
                    auto fb = read32(a, cfg.map.positionAddress, deadline);
                    if (!fb) {
                        if (fb.error().code == ErrorCode::Timeout && Clock::now() >= deadline)
                            return timeout(reason);
                        return fb.error();
                    }
                    const double um = static_cast<std::int32_t>(*fb) / a.stepsPerUm;
                    const double want = coord(*target, a.name);
                    if (std::abs(um - want) > cfg.positionWindowUm) {
                        settled = false;
                        std::ostringstream os;
                        os << "axis " << a.name << " says in position but feedback " << um
                           << " um is off target " << want << " um by more than the "
                           << cfg.positionWindowUm << " um window";
                        reason = os.str();
                    }
                }
            }
            if (observer && !settled && Clock::now() - lastObserved >= kObserveEvery) {
                // The position on the way, for whoever shows it; a failed read is not the
                // move's failure (the status poll decides that).
                if (auto on = readPosition(std::min(deadline, Clock::now() + kObserveEvery))) {
                    lastObserved = Clock::now();
                    observer(*on, lastObserved);
                }
            }
            const auto now = Clock::now();
            if (settled) {
                if (!settling)
                    settledSince = now;
                settling = true;
                if (now - settledSince >= cfg.settle)
                    return readPosition(stopDeadline());
            } else {
                settling = false;
            }
            if (now >= deadline)
                return timeout(reason);
            if (!stopSignal.waitUntil(std::min(now + cfg.pollInterval, deadline)))
                return makeError(ErrorCode::Cancelled, describe() + ": stopped");
        }
    }

    core::Error timeout(const std::string& reason) {
        sendStopAll(stopDeadline());
        return makeError(ErrorCode::Timeout, describe() + ": not settled before the deadline (" +
                                                 reason + "); stop sent");
    }
};

ModbusStage::ModbusStage(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

void ModbusStage::setMoveObserver(hw::MoveObserver observer) {
    impl_->observer = std::move(observer);
}
ModbusStage::~ModbusStage() = default;

core::Result<std::unique_ptr<ModbusStage>> ModbusStage::create(ModbusStageConfig cfg) {
    auto bad = [](const std::string& key, const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "stage." + key + ": " + what);
    };
    bool hasX = false, hasY = false;
    for (const auto& a : cfg.axes) {
        if (a.name != "x" && a.name != "y" && a.name != "z")
            return bad("axes", "unknown axis '" + a.name + "'");
        hasX |= a.name == "x";
        hasY |= a.name == "y";
        const std::string k = "axes." + a.name;
        if (a.slave < 1 || a.slave > 247)
            return bad(k + ".slave", "must be 1..247");
        if (!(a.stepsPerUm > 0) || !std::isfinite(a.stepsPerUm))
            return bad(k + ".steps_per_um", "must be > 0");
        if (!(a.minUm < a.maxUm))
            return bad(k + ".min_um", "must be below max_um");
    }
    if (!hasX || !hasY)
        return bad("axes", "needs an x and a y axis");
    if (cfg.map.moveAbs.empty() || cfg.map.stop.empty())
        return bad("preset", "the register map has no move or stop");
    if (!(cfg.speedUmPerS > 0))
        return bad("speed_um_per_s", "must be > 0");
    if (!(cfg.accelUmPerS2 > 0))
        return bad("accel_um_per_s2", "must be > 0");
    if (!(cfg.positionWindowUm > 0))
        return bad("position_window_um", "must be > 0");
    if (cfg.retries < 0 || cfg.retries > 10)
        return bad("retries", "must be 0..10");
    if (cfg.responseTimeout.count() <= 0)
        return bad("response_timeout_ms", "must be > 0");
    if (cfg.pollInterval.count() <= 0)
        cfg.pollInterval = std::chrono::milliseconds(1);

    auto impl = std::make_unique<Impl>();
    modbus_t* raw = nullptr;
    if (cfg.transport == ModbusStageConfig::Transport::Tcp) {
        if (cfg.port < 1 || cfg.port > 65535)
            return bad("port", "must be 1..65535");
        raw = modbus_new_tcp(cfg.host.c_str(), cfg.port);
    } else {
        if (cfg.device.empty())
            return bad("device", "missing serial device");
        if (cfg.parity != 'N' && cfg.parity != 'E' && cfg.parity != 'O')
            return bad("parity", "must be N, E or O");
        if (cfg.dataBits < 5 || cfg.dataBits > 8)
            return bad("data_bits", "must be 5..8");
        if (cfg.stopBits != 1 && cfg.stopBits != 2)
            return bad("stop_bits", "must be 1 or 2");
        raw = modbus_new_rtu(cfg.device.c_str(), cfg.baud, cfg.parity, cfg.dataBits, cfg.stopBits);
    }
    if (!raw)
        return makeError(ErrorCode::InvalidArgument,
                         "stage: " + std::string(modbus_strerror(errno)), errno);
    impl->ctx.reset(raw);
    impl->cfg = std::move(cfg);
    if (modbus_connect(raw) != 0) {
        const int e = errno;
        const ErrorCode code = e == ENOENT                          ? ErrorCode::NotFound
                               : classify(e) == Failure::Connection ? ErrorCode::Disconnected
                                                                    : ErrorCode::IoError;
        return makeError(code, impl->describe() + ": cannot connect: " + modbus_strerror(e), e);
    }
    impl->connected = true;
    return std::unique_ptr<ModbusStage>(new ModbusStage(std::move(impl)));
}

hw::StageLimits ModbusStage::limits() const {
    hw::StageLimits l;
    for (const auto& a : impl_->cfg.axes) {
        const hw::AxisRange r{a.minUm, a.maxUm};
        if (a.name == "x")
            l.x = r;
        else if (a.name == "y")
            l.y = r;
        else
            l.z = r;
    }
    return l;
}

core::Result<hw::StagePosition> ModbusStage::position(std::chrono::milliseconds timeout) {
    return impl_->readPosition(Clock::now() + timeout);
}

core::Result<hw::StagePosition> ModbusStage::moveTo(const hw::StagePosition& target,
                                                    std::chrono::milliseconds timeout) {
    impl_->stopSignal.clear();
    if (auto r = hw::checkWithinLimits(limits(), target); !r)
        return r.error();
    const auto deadline = Clock::now() + timeout;
    std::vector<MoveQuantities> moves;
    for (const auto& a : impl_->cfg.axes) {
        MoveQuantities q;
        q.positionSteps = std::llround(Impl::coord(target, a.name) * a.stepsPerUm);
        q.speedStepsPerS = impl_->cfg.speedUmPerS * a.stepsPerUm;
        q.accelStepsPerS2 = impl_->cfg.accelUmPerS2 * a.stepsPerUm;
        // Every axis's registers are checked before any axis moves: no half-started move.
        if (auto e = impl_->encodeSteps(impl_->cfg.map.moveAbs, a, q); !e)
            return e.error();
        moves.push_back(q);
    }
    for (std::size_t i = 0; i < impl_->cfg.axes.size(); ++i) {
        const auto& a = impl_->cfg.axes[i];
        const MoveQuantities& q = moves[i];
        if (auto r = impl_->runSteps(impl_->cfg.map.moveAbs, a, q, deadline); !r) {
            impl_->sendStopAll(impl_->stopDeadline());
            return r.error();
        }
        if (impl_->stopSignal.raised())
            return makeError(ErrorCode::Cancelled, impl_->describe() + ": stopped");
    }
    return impl_->waitSettled(&target, deadline);
}

core::Result<hw::StagePosition> ModbusStage::home(std::chrono::milliseconds timeout) {
    impl_->stopSignal.clear();
    if (impl_->cfg.map.home.empty())
        return makeError(ErrorCode::Unsupported,
                         "register map " + impl_->cfg.map.name + " has no home steps");
    const auto deadline = Clock::now() + timeout;
    for (const auto& a : impl_->cfg.axes)
        if (auto r = impl_->runSteps(impl_->cfg.map.home, a, {}, deadline); !r) {
            impl_->sendStopAll(impl_->stopDeadline());
            return r.error();
        }
    return impl_->waitSettled(nullptr, deadline);
}

void ModbusStage::stop() noexcept {
    impl_->stopSignal.raise();
    try {
        impl_->sendStopAll(impl_->stopDeadline());
    } catch (...) { // std::mutex::lock may throw system_error; stop() must not
    }
}

core::Result<hw::StageAlarm> ModbusStage::alarm(std::chrono::milliseconds timeout) {
    const auto deadline = Clock::now() + timeout;
    for (const auto& a : impl_->cfg.axes) {
        auto st = impl_->read16(a, impl_->cfg.map.status.address, deadline);
        if (!st)
            return st.error();
        auto code = impl_->alarmCode(a, deadline);
        if (!code)
            return code.error();
        if (*code != 0 || Impl::bit(*st, impl_->cfg.map.status.alarm))
            return hw::StageAlarm{true, *code, a.name};
    }
    return hw::StageAlarm{};
}

core::Result<void> ModbusStage::resetAlarm(std::chrono::milliseconds timeout) {
    if (impl_->cfg.map.alarmReset.empty())
        return makeError(ErrorCode::Unsupported,
                         "register map " + impl_->cfg.map.name + " has no alarm reset");
    const auto deadline = Clock::now() + timeout;
    for (const auto& a : impl_->cfg.axes)
        if (auto r = impl_->runSteps(impl_->cfg.map.alarmReset, a, {}, deadline); !r)
            return r;
    return {};
}

} // namespace slicestation::drivers
