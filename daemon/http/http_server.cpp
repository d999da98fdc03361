#include "http_server.hpp"

#include "connection.hpp"

#include <fcntl.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <charconv>
#include <cstdint>
#include <limits>
#include <utility>

namespace slicestation::daemon::http {

using core::ErrorCode;
using core::makeError;

namespace {
static_assert(L::kWorkers > L::kMaxEventStreams + 32, "room besides the event streams");
constexpr std::size_t kMaxBody = L::kMaxBody; // a plan of thousands of sections fits in far less

/// The connection the calling worker serves (request handlers run on it).
thread_local Connection* tConnection = nullptr;

/// Admission, before httplib reads a body: POSTs need the token and a Content-Length within
/// kMaxBody; other methods carry no body. \return false when refused (the answer is in `res`
/// and the connection closes after it).
bool admit(const httplib::Request& req, httplib::Response& res, const Authoriser& authorised) {
    Connection* conn = tConnection;
    auto refuse = [&](int status, const std::string& message) {
        if (!message.empty())
            sendError(res, status, message);
        res.set_header("Connection", "close");
        if (conn)
            conn->closeAfterResponse();
        return false;
    };
    std::optional<std::size_t> length;
    if (req.has_header("Content-Length")) {
        const std::string s = req.get_header_value("Content-Length");
        std::uint64_t v = 0;
        const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
        if (ec == std::errc::result_out_of_range)
            v = std::numeric_limits<std::uint64_t>::max();
        else if (ec != std::errc() || p != s.data() + s.size() ||
                 req.get_header_value_count("Content-Length") != 1)
            return refuse(400, "Content-Length: expected one number of bytes, got " + echo(s));
        length = static_cast<std::size_t>(std::min<std::uint64_t>(v, kMaxBody + 1));
    }
    const bool chunked = req.has_header("Transfer-Encoding");
    if (req.method == "POST") {
        if (!authorised(req, res))
            return refuse(401, "");
        if (chunked)
            return refuse(
                411, "a request body needs a Content-Length (chunked bodies are not accepted)");
        if (length && *length > kMaxBody)
            return refuse(413,
                          "request body over the limit of " + std::to_string(kMaxBody) + " bytes");
        if (conn)
            conn->allowBody(length);
        return true;
    }
    if (req.method != "GET" && req.method != "HEAD") {
        res.set_header("Allow", "GET, HEAD, POST");
        return refuse(405, "method " + echo(req.method) + " not allowed");
    }
    if (chunked || length.value_or(0) > 0)
        return refuse(400, "a " + req.method + " request has no body");
    if (conn)
        conn->allowBody(std::nullopt);
    return true;
}

} // namespace

Connection* currentConnection() noexcept {
    return tConnection;
}

core::Result<int> BoundedServer::bindTo(const std::string& host, int port) {
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
    addrinfo* found = nullptr;
    if (::getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &found) != 0 || !found)
        return makeError(ErrorCode::IoError, "HTTP: cannot resolve " + host);
    for (addrinfo* a = found; a && listenFd_ < 0; a = a->ai_next) {
        const int fd = ::socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
        if (fd < 0)
            continue;
        const int yes = 1;
        ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
        if (::bind(fd, a->ai_addr, a->ai_addrlen) == 0 && ::listen(fd, 64) == 0)
            listenFd_ = fd;
        else
            ::close(fd);
    }
    ::freeaddrinfo(found);
    if (listenFd_ < 0)
        return makeError(ErrorCode::IoError, "HTTP: cannot bind " + host + ":" +
                                                 std::to_string(port) +
                                                 " (in use, or not an address of this machine)");
    sockaddr_storage a{};
    socklen_t n = sizeof a;
    ::getsockname(listenFd_, reinterpret_cast<sockaddr*>(&a), &n);
    int bound = 0;
    if (a.ss_family == AF_INET)
        bound = ntohs(reinterpret_cast<sockaddr_in*>(&a)->sin_port);
    if (a.ss_family == AF_INET6)
        bound = ntohs(reinterpret_cast<sockaddr_in6*>(&a)->sin6_port);
    return bound;
}

core::Result<void> BoundedServer::startServing() {
    if (::pipe2(wake_.data(), O_CLOEXEC | O_NONBLOCK) != 0)
        return makeError(ErrorCode::IoError, "HTTP: cannot create a pipe");
    svr_sock_ = listenFd_; // httplib streams responses while this is valid
    pool_ = std::make_unique<httplib::ThreadPool>(static_cast<std::size_t>(L::kWorkers));
    acceptor_ = std::thread([this] { acceptLoop(); });
    return {};
}

void BoundedServer::stopServing() noexcept {
    if (stopping_.exchange(true))
        return;
    svr_sock_ = INVALID_SOCKET; // ends every streamed response at its next step
    if (wake_[1] >= 0) {
        [[maybe_unused]] const auto n = ::write(wake_[1], "x", 1);
    }
    if (acceptor_.joinable())
        acceptor_.join();
    {
        std::lock_guard lock(mutex_);
        for (int fd : open_)
            ::shutdown(fd, SHUT_RDWR); // wakes every wait on them
    }
    if (pool_)
        pool_->shutdown();
    pool_.reset();
    for (int& fd : wake_)
        if (fd >= 0)
            ::close(std::exchange(fd, -1));
    if (listenFd_ >= 0)
        ::close(std::exchange(listenFd_, -1));
}

void BoundedServer::acceptLoop() {
    for (;;) {
        std::array<pollfd, 2> p{pollfd{listenFd_, POLLIN, 0}, pollfd{wake_[0], POLLIN, 0}};
        if (::poll(p.data(), p.size(), -1) < 0 && errno != EINTR)
            break;
        if (stopping_ || p[1].revents)
            break;
        if (!(p[0].revents & POLLIN))
            continue;
        const int fd = ::accept4(listenFd_, nullptr, nullptr, SOCK_CLOEXEC);
        if (fd < 0) {
            if (errno == EMFILE || errno == ENFILE) // out of descriptors: let the others finish
                ::poll(nullptr, 0, 10);
            continue;
        }
        {
            std::lock_guard lock(mutex_);
            if (open_.size() >= static_cast<std::size_t>(L::kMaxConnections)) {
                static const std::string busy =
                    "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                    "Content-Length: 52\r\nConnection: close\r\nRetry-After: 5\r\n\r\n"
                    "{\"error\": \"too many connections; try again shortly\"}";
                [[maybe_unused]] auto n =
                    ::send(fd, busy.data(), busy.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
                ::close(fd);
                continue;
            }
            open_.insert(fd);
        }
        pool_->enqueue([this, fd] { serve(fd); });
    }
}

void BoundedServer::serve(int fd) noexcept {
    try {
        Connection conn(fd);
        tConnection = &conn;
        for (int left = L::kKeepAliveRequests; left > 0 && !stopping_; --left) {
            if (!conn.awaitRequest(L::kIdle))
                break;
            conn.beginRequest();
            bool closed = false;
            // Range headers are ignored (the whole content is sent, as HTTP allows): httplib
            // 0.11 bounds neither their number nor their offsets.
            const bool ok = process_request(conn, left == 1 || stopping_, closed,
                                            [](httplib::Request& req) { req.ranges.clear(); });
            if (!ok || closed || conn.mustClose()) {
                if (ok && conn.mustClose())
                    conn.lingerBeforeClose();
                break;
            }
        }
    } catch (...) { // nothing leaves a worker; the connection just ends
    }
    tConnection = nullptr;
    std::lock_guard lock(mutex_);
    open_.erase(fd);
    ::close(fd);
}

void installAdmission(httplib::Server& server, const Authoriser& authorised) {
    // Before any body is read (httplib runs this after the head, before reading content).
    server.set_pre_routing_handler(
        [authorised](const httplib::Request& req, httplib::Response& res) {
            return admit(req, res, authorised) ? httplib::Server::HandlerResponse::Unhandled
                                               : httplib::Server::HandlerResponse::Handled;
        });
    // A client that asks before sending its body is told the same, before it sends it.
    server.set_expect_100_continue_handler(
        [authorised](const httplib::Request& req, httplib::Response& res) {
            return admit(req, res, authorised) ? 100 : res.status;
        });
}

} // namespace slicestation::daemon::http
