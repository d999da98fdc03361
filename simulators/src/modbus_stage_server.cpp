#include "slicestation/sim/modbus_stage_server.hpp"

#include "slicestation/core/unique_fd.hpp"

#include <modbus/modbus.h>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <termios.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <map>
#include <mutex>
#include <thread>

namespace slicestation::sim {

using core::ErrorCode;
using core::makeError;
using core::UniqueFd;

core::Result<StageProtocol> stageProtocolFromName(const std::string& name) {
    if (name == "oriental-az")
        return StageProtocol::OrientalAz;
    if (name == "leadshine-pr")
        return StageProtocol::LeadshinePr;
    if (name == "applied-motion-q")
        return StageProtocol::AppliedMotionQ;
    return makeError(ErrorCode::NotFound,
                     "unknown protocol '" + name +
                         "' (known: oriental-az, leadshine-pr, applied-motion-q)");
}

namespace {

struct CtxDeleter {
    void operator()(modbus_t* c) const noexcept { modbus_free(c); }
};
struct MappingDeleter {
    void operator()(modbus_mapping_t* m) const noexcept { modbus_mapping_free(m); }
};

// Unit conversions the vendors document (see the driver presets for the same assumptions).
constexpr double kLeadshineStepsPerRev = 10'000;
constexpr double kAmpStepsPerRev = 20'000;

std::uint16_t crc16(const std::uint8_t* p, std::size_t n) {
    std::uint16_t crc = 0xFFFF;
    for (std::size_t i = 0; i < n; ++i) {
        crc ^= p[i];
        for (int b = 0; b < 8; ++b)
            crc = (crc & 1) ? static_cast<std::uint16_t>((crc >> 1) ^ 0xA001)
                            : static_cast<std::uint16_t>(crc >> 1);
    }
    return crc;
}

} // namespace

struct SlaveState {
    std::unique_ptr<modbus_mapping_t, MappingDeleter> mapping;
    SimAxis axis;
    std::uint16_t lastRin = 0, lastAlmRst = 0;
    double speed = 10'000,
           accel = 100'000; // steps/s, steps/s^2 of the last move (homing uses them)
    std::uint16_t* regs() { return mapping->tab_registers; }
};

struct ModbusStageServer::Impl {
    StageServerConfig cfg;
    mutable std::mutex mu;
    std::map<int, SlaveState> slaves;
    ReplyFault fault = ReplyFault::Drop;
    int faultCount = 0;
    std::chrono::milliseconds slowDelay{0};
    std::uint64_t requests = 0, writes = 0;

    std::unique_ptr<modbus_t, CtxDeleter> ctx;
    UniqueFd listenFd, ptyMaster, ptySlaveKeep, wakeRead, wakeWrite, capture, captureOut;
    std::vector<UniqueFd> clients;
    std::string ptyPath;
    int port = 0;
    std::vector<std::uint8_t> rtuBuf;
    std::atomic<bool> stopping{false};
    std::thread thread;

    static std::int32_t s32(const std::uint16_t* r, int a) {
        return static_cast<std::int32_t>((std::uint32_t(r[a]) << 16) | r[a + 1]);
    }
    static void put32(std::uint16_t* r, int a, std::int64_t v) {
        const auto u = static_cast<std::uint32_t>(static_cast<std::int32_t>(v));
        r[a] = static_cast<std::uint16_t>(u >> 16);
        r[a + 1] = static_cast<std::uint16_t>(u & 0xFFFF);
    }

    void refresh(SlaveState& s, core::TimePoint now) {
        const AxisState st = s.axis.state(now);
        auto* r = s.regs();
        const auto fb = std::llround(st.feedbackSteps);
        const bool alarm = st.alarmCode != 0;
        switch (cfg.protocol) {
        case StageProtocol::OrientalAz:
            r[0x7E] = 0;
            r[0x7F] = static_cast<std::uint16_t>((st.homeEnd << 4) | ((!st.moving && !alarm) << 5) |
                                                 (alarm << 7) | (st.moving << 13) |
                                                 (st.inPosition << 14));
            put32(r, 0x80, st.alarmCode);
            put32(r, 0xCC, fb);
            put32(r, 0x120, std::llround(st.commandSteps));
            break;
        case StageProtocol::LeadshinePr:
            r[0x1003] = static_cast<std::uint16_t>(alarm | (1 << 1) | (st.moving << 2) |
                                                   ((!st.moving) << 4) | (st.inPosition << 5) |
                                                   (st.homeEnd << 6));
            put32(r, 0x602C, fb);
            r[0x2203] = static_cast<std::uint16_t>(st.alarmCode);
            break;
        case StageProtocol::AppliedMotionQ:
            r[0] = static_cast<std::uint16_t>(st.alarmCode);
            r[1] = static_cast<std::uint16_t>(0x0001 | (alarm ? 0x0204 : 0) | (st.inPosition << 3) |
                                              (st.moving << 4) | (st.homing << 10));
            put32(r, 4, fb);
            put32(r, 6, fb);
            break;
        }
    }

    void afterWrite(SlaveState& s, int addr, int n, core::TimePoint now) {
        auto covers = [&](int a) { return a >= addr && a < addr + n; };
        auto* r = s.regs();
        const double here = s.axis.state(now).commandSteps;
        switch (cfg.protocol) {
        case StageProtocol::OrientalAz: // HM-60262E direct data operation
            if (covers(0x67) && s32(r, 0x66) == 1) {
                const auto type = s32(r, 0x5A);
                s.speed = std::max(1, s32(r, 0x5E));
                s.accel = std::max(1, s32(r, 0x60)); // 0.001 kHz/s = 1 Hz/s
                const double pos = s32(r, 0x5C);
                if (type == 1)
                    s.axis.startMove(pos, s.speed, s.accel, now);
                else if (type == 2 || type == 3)
                    s.axis.startMove(here + pos, s.speed, s.accel, now);
            }
            if (covers(0x7D)) {
                const std::uint16_t rising = r[0x7D] & ~s.lastRin;
                if (rising & 0x10)
                    s.axis.startHome(s.speed, s.accel, now);
                if (rising & 0x20)
                    s.axis.halt(now);
                if (rising & 0x80)
                    s.axis.resetAlarm(now);
                s.lastRin = r[0x7D];
            }
            if (covers(0x181)) {
                if (r[0x181] == 1 && s.lastAlmRst == 0)
                    s.axis.resetAlarm(now);
                s.lastAlmRst = r[0x181];
            }
            break;
        case StageProtocol::LeadshinePr:
            if (covers(0x6002)) {
                const std::uint16_t v = r[0x6002];
                if (v >= 0x10 && v <= 0x1F) {
                    const std::uint16_t mode = r[0x6200];
                    s.speed = std::max(1.0, r[0x6203] * kLeadshineStepsPerRev / 60.0);
                    const double ms = r[0x6204];
                    s.accel =
                        ms > 0 ? (1000.0 * kLeadshineStepsPerRev / 60.0) / (ms / 1000.0) : 1e6;
                    const double pos = s32(r, 0x6201);
                    if ((mode & 0x0F) == 1)
                        s.axis.startMove((mode & 0x40) ? here + pos : pos, s.speed, s.accel, now);
                } else if (v == 0x20) {
                    s.axis.startHome(s.speed, s.accel, now);
                } else if (v == 0x40) {
                    s.axis.halt(now);
                }
                r[0x6002] = 0x0100;
            }
            if (covers(0x1801) && r[0x1801] == 0x1111) {
                s.axis.resetAlarm(now);
                r[0x1801] = 0;
            }
            break;
        case StageProtocol::AppliedMotionQ: // 920-0072 opcode register 40125
            if (covers(124)) {
                const std::uint16_t op = r[124];
                s.speed = std::max(1.0, r[29] / 240.0 * kAmpStepsPerRev);
                s.accel = std::max(1.0, r[27] / 6.0 * kAmpStepsPerRev);
                const double di = s32(r, 30);
                if (op == 0x67)
                    s.axis.startMove(di, s.speed, s.accel, now);
                else if (op == 0x66)
                    s.axis.startMove(here + di, s.speed, s.accel, now);
                else if (op == 0x6E)
                    s.axis.startHome(s.speed, s.accel, now);
                else if (op == 0xBA)
                    s.axis.resetAlarm(now);
                else if (op == 0xE1 || op == 0xE2)
                    s.axis.halt(now);
                r[124] = 0;
            }
            break;
        }
    }

    // Handles one complete request; writes the reply (or not) to `out`.
    void handle(const std::uint8_t* req, int len, int out) {
        const int off = modbus_get_header_length(ctx.get());
        if (len < off + 5)
            return;
        const int slaveId = req[off - 1];
        const int fc = req[off];
        const int addr = (req[off + 1] << 8) | req[off + 2];
        const int n = (fc == 6 || fc == 5) ? 1 : (req[off + 3] << 8) | req[off + 4];
        std::vector<std::uint8_t> reply(MODBUS_MAX_ADU_LENGTH);
        int replyLen = 0;
        bool drop = false, corrupt = false, truncated = false;
        std::chrono::milliseconds delay{0};
        {
            std::lock_guard lock(mu);
            auto it = slaves.find(slaveId);
            if (it == slaves.end())
                return; // another slave's request: not ours to answer
            ++requests;
            const bool isWrite = fc == 5 || fc == 6 || fc == 15 || fc == 16;
            if (isWrite)
                ++writes;
            const auto now = std::chrono::steady_clock::now();
            refresh(it->second, now);
            bool exception = false;
            if (faultCount != 0) {
                if (faultCount > 0)
                    --faultCount;
                drop = fault == ReplyFault::Drop;
                corrupt = fault == ReplyFault::Corrupt;
                exception = fault == ReplyFault::Exception;
                truncated = fault == ReplyFault::Truncated;
                if (fault == ReplyFault::Slow)
                    delay = slowDelay;
            }
            modbus_set_slave(ctx.get(), slaveId);
            modbus_set_socket(ctx.get(), captureOut.get());
            int rc;
            if (exception) {
                rc = modbus_reply_exception(ctx.get(), req, MODBUS_EXCEPTION_SLAVE_OR_SERVER_BUSY);
            } else {
                rc = modbus_reply(ctx.get(), req, len, it->second.mapping.get());
                if (rc > 0 && isWrite)
                    afterWrite(it->second, addr, n, now);
            }
            if (rc > 0)
                replyLen = static_cast<int>(::read(capture.get(), reply.data(), reply.size()));
        }
        if (drop || replyLen <= 0)
            return;
        if (truncated)
            replyLen = std::max(1, replyLen - 3); // the last bytes never come
        if (corrupt) {
            if (cfg.tcp)
                reply[1] ^= 0x5A; // transaction id: the client rejects the header
            else
                reply[static_cast<std::size_t>(replyLen) - 1] ^= 0xFF; // CRC
        }
        if (delay.count() > 0) {
            pollfd p{wakeRead.get(), POLLIN, 0};
            ::poll(&p, 1, static_cast<int>(delay.count()));
            if (stopping)
                return;
        }
        // A TCP client may have hung up meanwhile (a driver reconnects after a corrupt reply):
        // that is an EPIPE for this reply, never a SIGPIPE that ends the process serving.
        if (cfg.tcp)
            (void)!::send(out, reply.data(), static_cast<std::size_t>(replyLen), MSG_NOSIGNAL);
        else
            (void)!::write(out, reply.data(), static_cast<std::size_t>(replyLen));
    }

    void rtuRead() {
        std::uint8_t tmp[512];
        const ssize_t got = ::read(ptyMaster.get(), tmp, sizeof tmp);
        if (got <= 0)
            return;
        rtuBuf.insert(rtuBuf.end(), tmp, tmp + got);
        while (rtuBuf.size() >= 2) {
            const int fc = rtuBuf[1];
            std::size_t need;
            if (fc >= 1 && fc <= 6)
                need = 8;
            else if (fc == 15 || fc == 16) {
                if (rtuBuf.size() < 7)
                    break;
                need = 9u + rtuBuf[6];
            } else {
                rtuBuf.clear();
                break;
            }
            if (rtuBuf.size() < need)
                break;
            const std::uint16_t crc = crc16(rtuBuf.data(), need - 2);
            if ((rtuBuf[need - 2] | (rtuBuf[need - 1] << 8)) != crc) { // line noise: resync
                rtuBuf.clear();
                break;
            }
            std::vector<std::uint8_t> frame(rtuBuf.begin(),
                                            rtuBuf.begin() + static_cast<long>(need));
            rtuBuf.erase(rtuBuf.begin(), rtuBuf.begin() + static_cast<long>(need));
            handle(frame.data(), static_cast<int>(need), ptyMaster.get());
        }
    }

    void tcpClient(std::size_t i) {
        std::uint8_t req[MODBUS_TCP_MAX_ADU_LENGTH];
        modbus_set_socket(ctx.get(), clients[i].get());
        const int len = modbus_receive(ctx.get(), req);
        if (len < 0) {
            clients.erase(clients.begin() + static_cast<long>(i));
            return;
        }
        if (len > 0)
            handle(req, len, clients[i].get());
    }

    void run() {
        while (!stopping) {
            std::vector<pollfd> fds{{wakeRead.get(), POLLIN, 0}};
            if (cfg.tcp) {
                fds.push_back({listenFd.get(), POLLIN, 0});
                for (auto& c : clients)
                    fds.push_back({c.get(), POLLIN, 0});
            } else {
                fds.push_back({ptyMaster.get(), POLLIN, 0});
            }
            // An incomplete RTU frame followed by silence is discarded (the 3.5-char gap).
            const int rc = ::poll(fds.data(), fds.size(), rtuBuf.empty() ? 500 : 50);
            if (stopping)
                break;
            if (rc == 0) {
                rtuBuf.clear();
                continue;
            }
            if (rc < 0)
                continue;
            if (!cfg.tcp) {
                if (fds[1].revents & POLLIN)
                    rtuRead();
                continue;
            }
            if (fds[1].revents & POLLIN) {
                const int c = ::accept4(listenFd.get(), nullptr, nullptr, SOCK_CLOEXEC);
                if (c >= 0)
                    clients.emplace_back(c);
            }
            for (std::size_t i = fds.size() - 1; i >= 2; --i)
                if (fds[i].revents & (POLLIN | POLLHUP | POLLERR))
                    tcpClient(i - 2);
        }
    }
};

ModbusStageServer::ModbusStageServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

ModbusStageServer::~ModbusStageServer() {
    stop();
}

core::Result<std::unique_ptr<ModbusStageServer>> ModbusStageServer::create(StageServerConfig cfg) {
    auto io = [](const std::string& what) {
        const int e = errno;
        return makeError(ErrorCode::IoError, "stage-sim: " + what + ": " + std::strerror(e), e);
    };
    if (cfg.slaves.empty())
        return makeError(ErrorCode::InvalidArgument, "stage-sim: no slaves");
    auto impl = std::make_unique<Impl>();
    impl->cfg = cfg;
    for (int id : cfg.slaves) {
        if (id < 1 || id > 247)
            return makeError(ErrorCode::InvalidArgument, "stage-sim: slave ids are 1..247");
        SlaveState s;
        s.mapping.reset(modbus_mapping_new(0, 0, 0x10000, 0));
        if (!s.mapping)
            return io("modbus_mapping_new");
        impl->slaves.emplace(id, std::move(s));
    }
    int wake[2];
    if (::pipe2(wake, O_CLOEXEC | O_NONBLOCK) != 0)
        return io("pipe");
    impl->wakeRead.reset(wake[0]);
    impl->wakeWrite.reset(wake[1]);
    int sp[2];
    if (::socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0, sp) != 0)
        return io("socketpair");
    impl->capture.reset(sp[0]);
    impl->captureOut.reset(sp[1]);

    if (cfg.tcp) {
        impl->ctx.reset(modbus_new_tcp("127.0.0.1", cfg.tcpPort));
        if (!impl->ctx)
            return io("modbus_new_tcp");
        const int fd = modbus_tcp_listen(impl->ctx.get(), 4);
        if (fd < 0)
            return io("listen on 127.0.0.1:" + std::to_string(cfg.tcpPort));
        impl->listenFd.reset(fd);
        sockaddr_in addr{};
        socklen_t alen = sizeof addr;
        if (::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &alen) != 0)
            return io("getsockname");
        impl->port = ntohs(addr.sin_port);
        modbus_set_indication_timeout(impl->ctx.get(), 1, 0);
    } else {
        // Replies are generated by an RTU context writing into the capture socket; requests
        // are framed here because libmodbus' RTU server answers a single slave id only.
        impl->ctx.reset(modbus_new_rtu("/dev/null", 115200, 'N', 8, 1));
        if (!impl->ctx)
            return io("modbus_new_rtu");
        const int m = ::posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
        if (m < 0)
            return io("posix_openpt");
        impl->ptyMaster.reset(m);
        if (::grantpt(m) != 0 || ::unlockpt(m) != 0)
            return io("grantpt/unlockpt");
        char name[128];
        if (::ptsname_r(m, name, sizeof name) != 0)
            return io("ptsname");
        impl->ptyPath = name;
        // Keep the slave side open (no hang-up while no client is connected) and raw.
        const int s = ::open(name, O_RDWR | O_NOCTTY | O_CLOEXEC);
        if (s < 0)
            return io("open " + impl->ptyPath);
        impl->ptySlaveKeep.reset(s);
        termios t{};
        if (::tcgetattr(s, &t) == 0) {
            ::cfmakeraw(&t);
            ::tcsetattr(s, TCSANOW, &t);
        }
    }
    auto server = std::unique_ptr<ModbusStageServer>(new ModbusStageServer(std::move(impl)));
    Impl* raw = server->impl_.get();
    server->impl_->thread = std::thread([raw] { raw->run(); });
    return server;
}

int ModbusStageServer::tcpPort() const {
    return impl_->port;
}
std::string ModbusStageServer::rtuDevice() const {
    return impl_->ptyPath;
}

void ModbusStageServer::injectReplyFault(ReplyFault fault, int count,
                                         std::chrono::milliseconds slowDelay) {
    std::lock_guard lock(impl_->mu);
    impl_->fault = fault;
    impl_->faultCount = count;
    impl_->slowDelay = slowDelay;
}

void ModbusStageServer::clearReplyFaults() {
    std::lock_guard lock(impl_->mu);
    impl_->faultCount = 0;
}

void ModbusStageServer::setStall(int slave, bool stall) {
    std::lock_guard lock(impl_->mu);
    if (auto it = impl_->slaves.find(slave); it != impl_->slaves.end())
        it->second.axis.setStall(stall);
}

void ModbusStageServer::armAlarm(int slave, std::uint32_t code) {
    std::lock_guard lock(impl_->mu);
    if (auto it = impl_->slaves.find(slave); it != impl_->slaves.end())
        it->second.axis.armAlarm(code);
}

void ModbusStageServer::setDriftSteps(int slave, double steps) {
    std::lock_guard lock(impl_->mu);
    if (auto it = impl_->slaves.find(slave); it != impl_->slaves.end())
        it->second.axis.setDriftSteps(steps);
}

AxisState ModbusStageServer::axisState(int slave) const {
    std::lock_guard lock(impl_->mu);
    if (auto it = impl_->slaves.find(slave); it != impl_->slaves.end())
        return it->second.axis.state(std::chrono::steady_clock::now());
    return {};
}

std::uint64_t ModbusStageServer::requestCount() const {
    std::lock_guard lock(impl_->mu);
    return impl_->requests;
}

std::uint64_t ModbusStageServer::writeCount() const {
    std::lock_guard lock(impl_->mu);
    return impl_->writes;
}

void ModbusStageServer::stop() noexcept {
    if (!impl_ || impl_->stopping.exchange(true))
        return;
    const char c = 1;
    (void)!::write(impl_->wakeWrite.get(), &c, 1);
    if (impl_->thread.joinable())
        impl_->thread.join();
    // A stopped server is a device that went away: connections close, the port refuses.
    impl_->clients.clear();
    impl_->listenFd.reset();
    impl_->ptyMaster.reset();
    impl_->ptySlaveKeep.reset();
}

} // namespace slicestation::sim
