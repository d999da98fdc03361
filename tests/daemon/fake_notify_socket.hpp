#pragma once
// Test support: what systemd does for Type=notify services, a unix datagram socket whose path
// goes into NOTIFY_SOCKET. Used by the notifier unit tests and the daemon process tests.
#include "../common/test_dir.hpp"
#include "slicestation/core/unique_fd.hpp"

#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <chrono>
#include <cstring>
#include <filesystem>
#include <optional>
#include <string>

namespace slicestation::test {

inline constexpr std::chrono::seconds kEventDeadline{
    10}; // generous: only a broken build waits this long

/// What systemd does: a unix datagram socket whose path goes into NOTIFY_SOCKET.
class FakeNotifySocket {
public:
    FakeNotifySocket() {
        path_ = dir_.path() / "notify";
        fd_.reset(::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0));
        sockaddr_un addr{};
        addr.sun_family = AF_UNIX;
        std::strncpy(addr.sun_path, path_.c_str(), sizeof(addr.sun_path) - 1);
        bound_ = ::bind(fd_.get(), reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0;
    }
    ~FakeNotifySocket() { fd_.reset(); } // before dir_ goes with the socket file
    bool bound() const { return bound_; }
    const std::filesystem::path& path() const { return path_; }

    /// The next datagram, waiting at most `timeout` (poll); nullopt when none came.
    std::optional<std::string> receive(std::chrono::milliseconds timeout = kEventDeadline) {
        pollfd p{fd_.get(), POLLIN, 0};
        if (::poll(&p, 1, static_cast<int>(timeout.count())) != 1)
            return std::nullopt;
        char buf[4096];
        const ssize_t n = ::recv(fd_.get(), buf, sizeof(buf), 0);
        if (n < 0)
            return std::nullopt;
        return std::string(buf, static_cast<std::size_t>(n));
    }
    /// A datagram already queued, without waiting.
    std::optional<std::string> pending() { return receive(std::chrono::milliseconds(0)); }

private:
    testing_dir::ScratchDir dir_{"notify"};
    std::filesystem::path path_;
    core::UniqueFd fd_;
    bool bound_ = false;
};

} // namespace slicestation::test
