// HTTP requests from the network: each input is sent as raw bytes to the station's real API
// (cpp-httplib server, every route) on 127.0.0.1, and the answer read to the end. The station
// behind it is whole (journal, simulated stage and camera, built-in atlas) but not started, so
// a submitted plan is validated and journaled without a scan. A crash, hang or leak of the
// server is a finding; the seed corpus holds one request per route, with and without the token.
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/http/http_api.hpp"
#include "slicestation/daemon/station/station.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include "fuzz_common.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>

using namespace slicestation;

namespace {

struct Rig {
    std::unique_ptr<daemon::Station> station;
    std::unique_ptr<daemon::HttpApi> api;
};

[[noreturn]] void die(const std::string& what) {
    std::fprintf(stderr, "fuzz_http setup: %s\n", what.c_str());
    std::abort();
}

Rig& rig() {
    static Rig* r = [] {
        auto* rig = new Rig();
        sim::SimStageConfig sc;
        sc.clock = std::make_shared<core::VirtualClock>();
        auto stage = sim::SimStage::create(sc);
        if (!stage)
            die(stage.error().message);
        sim::VirtualSlideSpec spec;
        spec.columns = 1;
        spec.umPerPx = 20;
        spec.sections.push_back({0.5, "", 7});
        auto slide = sim::makeVirtualSlide(spec);
        if (!slide)
            die(slide.error().message);
        sim::SimCameraConfig cc;
        cc.sensorUmPerPx = 10;
        cc.stagePosition = [] { return hw::StagePosition{}; };
        auto camera = sim::SimCamera::create(*slide, cc);
        if (!camera)
            die(camera.error().message);
        auto doc = daemon::parseDocument(
            "[daemon]\ntoken = \"fuzz-token-0123456789\"\n[scan]\num_per_px = 10\n",
            daemon::DocumentFormat::Toml, "station.toml");
        if (!doc)
            die(doc.error().message);
        auto settings = daemon::parseDaemonSettings(*doc, "station.toml");
        if (!settings)
            die(settings.error().message);
        daemon::StationParts parts;
        parts.stage = std::move(*stage);
        parts.camera = std::move(*camera);
        parts.simulatedStage = parts.simulatedCamera = true;
        parts.settings = *settings;
        parts.stateDir = fuzz::scratchDir() / "state";
        parts.freeSpace = [](const std::filesystem::path&) -> core::Result<std::uint64_t> {
            return 100ull << 30;
        };
        auto st = daemon::Station::create(std::move(parts));
        if (!st)
            die(st.error().message);
        rig->station = std::move(*st);
        auto api = daemon::HttpApi::start(*rig->station, "127.0.0.1", 0, "fuzz-token-0123456789");
        if (!api)
            die(api.error().message);
        rig->api = std::move(*api);
        return rig;
    }();
    return *r;
}

} // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const int port = rig().api->port();
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (fd < 0)
        die(std::string("socket: ") + std::strerror(errno));
    timeval tv{5, 0};
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv);
    // Each input is a connection that ends in TIME_WAIT for 60 s on this side (it closes
    // first). At a thousand inputs a second one source address would run out of ephemeral
    // ports (28,232 on Debian) within the run, and connect() fail with EADDRNOTAVAIL: CI's
    // fuzz_http failed so on 2026-12-03. The source address cycles through 127.0.1.0/24..
    // 127.0.64.0/24 instead; the whole of 127/8 is this host.
    static std::uint32_t next = 0;
    sockaddr_in from{};
    from.sin_family = AF_INET;
    from.sin_addr.s_addr = htonl((127u << 24) + 256u + next++ % (64u * 256u));
    if (::bind(fd, reinterpret_cast<sockaddr*>(&from), sizeof from) != 0)
        die(std::string("bind: ") + std::strerror(errno));
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<std::uint16_t>(port));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        // A signal (libFuzzer's timers) may interrupt the wait for the handshake; the
        // connection goes on, and is awaited here.
        if (errno != EINTR && errno != EINPROGRESS)
            die(std::string("connect: ") + std::strerror(errno));
        pollfd p{fd, POLLOUT, 0};
        int err = 0;
        socklen_t len = sizeof err;
        while (::poll(&p, 1, 5000) < 0 && errno == EINTR) {
        }
        if (!(p.revents & POLLOUT) || ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &len) != 0 ||
            err != 0)
            die(std::string("connect: ") + std::strerror(err != 0 ? err : ETIMEDOUT));
    }
    std::size_t sent = 0;
    while (sent < size) {
        const auto n = ::send(fd, data + sent, size - sent, MSG_NOSIGNAL);
        if (n <= 0)
            break; // the server may answer and close before reading everything
        sent += static_cast<std::size_t>(n);
    }
    ::shutdown(fd, SHUT_WR);
    char buf[16384];
    while (::recv(fd, buf, sizeof buf, 0) > 0) {
    }
    ::close(fd);
    return 0;
}
