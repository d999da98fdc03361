// What the stage driver reads from outside: the drives' Modbus replies and a register-map file.
//
// The first byte chooses. Even: the rest is a register-map file (TOML, `stage.map_file`), parsed
// by parseRegisterMap. Odd: the rest is a script of replies. A Modbus TCP server on 127.0.0.1
// answers each request the real ModbusStage driver sends (position, alarm, move, reset, home,
// stop) with the next step of the script: a well-framed reply carrying fuzzed register values,
// an exception with a fuzzed code, a frame with the right header and a fuzzed body, raw bytes,
// silence (the driver's response timeout), or a closed connection; when the script ends the
// server closes every connection. Whatever comes back, the driver must return a value or an
// error, never crash, hang, leak or report a position that is not a finite number.
#include "slicestation/drivers/modbus_stage.hpp"
#include "slicestation/drivers/register_map.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

using namespace slicestation;

namespace {

[[noreturn]] void die(const char* what) {
    std::fprintf(stderr, "fuzz_modbus setup: %s\n", what);
    std::abort();
}

/// Reads exactly `n` bytes within `ms`; false on timeout, error or a closed peer.
bool readExactly(int fd, std::uint8_t* out, std::size_t n, int ms) {
    std::size_t got = 0;
    while (got < n) {
        pollfd p{fd, POLLIN, 0};
        if (::poll(&p, 1, ms) <= 0)
            return false;
        const ssize_t r = ::recv(fd, out + got, n - got, 0);
        if (r <= 0)
            return false;
        got += static_cast<std::size_t>(r);
    }
    return true;
}

void sendAll(int fd, const std::vector<std::uint8_t>& bytes) {
    std::size_t sent = 0;
    while (sent < bytes.size()) {
        const ssize_t w = ::send(fd, bytes.data() + sent, bytes.size() - sent, MSG_NOSIGNAL);
        if (w <= 0)
            return;
        sent += static_cast<std::size_t>(w);
    }
}

/// The scripted server: one connection at a time (the driver holds one), each request answered
/// by the next step of the current input's script.
class ScriptedServer {
public:
    ScriptedServer() {
        listenFd_ = ::socket(AF_INET, SOCK_STREAM, 0);
        if (listenFd_ < 0)
            die("socket");
        const int one = 1;
        ::setsockopt(listenFd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
        sockaddr_in a{};
        a.sin_family = AF_INET;
        a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        if (::bind(listenFd_, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0)
            die("bind");
        if (::listen(listenFd_, 8) != 0)
            die("listen");
        socklen_t len = sizeof a;
        ::getsockname(listenFd_, reinterpret_cast<sockaddr*>(&a), &len);
        port_ = ntohs(a.sin_port);
        thread_ = std::thread([this] { serve(); });
        thread_.detach(); // lives as long as the fuzzing process
    }
    int port() const { return port_; }

    /// A new input: its script replaces the last one's, and any connection of the last input is
    /// closed before the driver of this one connects.
    void load(const std::uint8_t* data, std::size_t size) {
        std::lock_guard lock(mutex_);
        script_.assign(data, data + size);
        pos_ = 0;
        ++generation_;
    }

private:
    /// Next script byte, or -1 when the script is over.
    int next() {
        std::lock_guard lock(mutex_);
        return pos_ < script_.size() ? script_[pos_++] : -1;
    }
    std::uint64_t generation() {
        std::lock_guard lock(mutex_);
        return generation_;
    }

    void serve() {
        for (;;) {
            const int fd = ::accept(listenFd_, nullptr, nullptr);
            if (fd < 0)
                continue;
            const std::uint64_t gen = generation();
            handle(fd, gen);
            ::close(fd);
        }
    }

    void handle(int fd, std::uint64_t gen) {
        for (;;) {
            std::uint8_t head[7];
            // The driver sends its next request at once; a quiet second means it is gone.
            if (!readExactly(fd, head, 7, 1000))
                return;
            if (generation() != gen)
                return;
            const int length = head[4] << 8 | head[5];
            if (length < 2 || length > 260)
                return;
            std::vector<std::uint8_t> pdu(static_cast<std::size_t>(length - 1));
            if (!readExactly(fd, pdu.data(), pdu.size(), 1000))
                return;
            const int step = next();
            if (step < 0)
                return; // the script is over: close
            if (!answer(fd, head, pdu, step))
                return;
        }
    }

    /// One reply; false closes the connection.
    bool answer(int fd, const std::uint8_t* head, const std::vector<std::uint8_t>& pdu, int step) {
        const std::uint8_t fc = pdu[0];
        std::vector<std::uint8_t> body; // unit id onwards
        body.push_back(head[6]);
        const auto byte = [this] {
            const int b = next();
            return static_cast<std::uint8_t>(b < 0 ? 0 : b);
        };
        switch (step % 6) {
        case 0: // a well-framed reply with fuzzed values
            body.push_back(fc);
            if (fc == 0x03 || fc == 0x04) {
                const int qty = pdu.size() >= 5 ? (pdu[3] << 8 | pdu[4]) : 1;
                const int n = std::min(qty, 125);
                body.push_back(static_cast<std::uint8_t>(2 * n));
                for (int i = 0; i < 2 * n; ++i)
                    body.push_back(byte());
            } else {
                for (std::size_t i = 1; i < std::min<std::size_t>(pdu.size(), 5); ++i)
                    body.push_back(pdu[i]);
            }
            break;
        case 1: // an exception
            body.push_back(static_cast<std::uint8_t>(fc | 0x80));
            body.push_back(byte());
            break;
        case 2: { // the right header, a fuzzed body
            const int n = byte() % 40;
            for (int i = 0; i < n; ++i)
                body.push_back(byte());
            break;
        }
        case 3: { // raw bytes, no framing at all
            const int n = byte() % 40;
            std::vector<std::uint8_t> raw;
            for (int i = 0; i < n; ++i)
                raw.push_back(byte());
            sendAll(fd, raw);
            return true;
        }
        case 4: // silence: the driver's response timeout
            return true;
        default: // the drive hangs up
            return false;
        }
        std::vector<std::uint8_t> frame(head, head + 4);
        frame.push_back(static_cast<std::uint8_t>(body.size() >> 8));
        frame.push_back(static_cast<std::uint8_t>(body.size() & 0xff));
        frame.insert(frame.end(), body.begin(), body.end());
        sendAll(fd, frame);
        return true;
    }

    int listenFd_ = -1;
    int port_ = 0;
    std::thread thread_;
    std::mutex mutex_;
    std::vector<std::uint8_t> script_;
    std::size_t pos_ = 0;
    std::uint64_t generation_ = 0;
};

ScriptedServer& server() {
    static ScriptedServer* s = new ScriptedServer(); // never destroyed: its thread runs to the end
    return *s;
}

void check(const core::Result<hw::StagePosition>& p) {
    if (p && !(std::isfinite(p->xUm) && std::isfinite(p->yUm) && std::isfinite(p->zUm))) {
        std::fprintf(stderr, "a position that is not finite: %g %g %g\n", p->xUm, p->yUm, p->zUm);
        std::abort();
    }
}

void driveTheStage(const std::uint8_t* data, std::size_t size) {
    server().load(data, size);
    drivers::ModbusStageConfig cfg;
    cfg.transport = drivers::ModbusStageConfig::Transport::Tcp;
    cfg.host = "127.0.0.1";
    cfg.port = server().port();
    cfg.map = drivers::presetMap("oriental-az").value();
    cfg.axes = {{"x", 1, 2.0, 0, 75'000}, {"y", 2, 2.0, 0, 50'000}, {"z", 3, 10.0, 0, 5'000}};
    cfg.settle = std::chrono::milliseconds(1);
    cfg.pollInterval = std::chrono::milliseconds(1);
    cfg.responseTimeout = std::chrono::milliseconds(5);
    cfg.retries = 1;
    auto stage = drivers::ModbusStage::create(cfg);
    if (!stage)
        return; // connection refused is a legitimate answer
    using std::chrono::milliseconds;
    check((*stage)->position(milliseconds(30)));
    (void)(*stage)->alarm(milliseconds(30));
    check((*stage)->moveTo({1'000, 2'000, 100}, milliseconds(40)));
    (void)(*stage)->resetAlarm(milliseconds(30));
    check((*stage)->home(milliseconds(40)));
    (*stage)->stop();
    check((*stage)->position(milliseconds(30)));
}

} // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0)
        return 0;
    if (data[0] % 2 == 0) {
        const std::string_view text(reinterpret_cast<const char*>(data + 1), size - 1);
        auto map = drivers::parseRegisterMap(text, "fuzz.toml");
        if (!map)
            return 0;
        // A map that parses encodes every move the station file allows (speeds 1e-15..1e13
        // steps/s, accelerations 1e-15..1e15 steps/s^2) into a value that fits its register or
        // an OutOfRange error, never an overflow.
        const drivers::MoveQuantities moves[] = {{0, 1, 1},
                                                 {-2'000'000'000, 1e-15, 1e-15},
                                                 {2'000'000'000, 1e13, 1e15},
                                                 {123'456, 2e5, 4e5}};
        for (const auto* steps : {&map->moveAbs, &map->home, &map->stop, &map->alarmReset})
            for (const auto& step : *steps)
                for (const auto& v : step.values)
                    for (const auto& q : moves)
                        for (bool wide : {false, true}) {
                            auto e = drivers::encodeChecked(*map, v, q, wide);
                            if (e && (*e < (wide ? -2147483648LL : 0) ||
                                      *e > (wide ? 4294967295LL : 65535))) {
                                std::fprintf(stderr, "encoded %lld does not fit\n",
                                             static_cast<long long>(*e));
                                std::abort();
                            }
                        }
        return 0;
    }
    driveTheStage(data + 1, size - 1);
    return 0;
}
