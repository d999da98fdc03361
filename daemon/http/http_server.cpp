#include "http_server.hpp"

#include "connection.hpp"

#include <fcntl.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <charconv>
#include <cstdint>
#include <limits>
#include <optional>
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
        acceptor_.join(); // it closed the connections parked with it
    {
        std::lock_guard lock(mutex_);
        for (int fd : open_)
            ::shutdown(fd, SHUT_RDWR); // wakes every wait on them
    }
    if (pool_)
        pool_->shutdown();
    pool_.reset();
    {
        std::lock_guard lock(mutex_); // parked after the acceptor ended
        for (const Parked& p : handedOver_) {
            open_.erase(p.fd);
            ::close(p.fd);
        }
        handedOver_.clear();
    }
    for (int& fd : wake_)
        if (fd >= 0)
            ::close(std::exchange(fd, -1));
    if (listenFd_ >= 0)
        ::close(std::exchange(listenFd_, -1));
}

void BoundedServer::acceptLoop() {
    std::vector<Parked> parked, kept; // this thread's own
    std::vector<pollfd> p;
    while (!stopping_) {
        {
            std::lock_guard lock(mutex_);
            for (Parked& h : handedOver_)
                parked.push_back(std::move(h));
            handedOver_.clear();
        }
        p.assign({pollfd{listenFd_, POLLIN, 0}, pollfd{wake_[0], POLLIN, 0}});
        auto next = Clock::time_point::max();
        for (const Parked& c : parked) {
            p.push_back(pollfd{c.fd, POLLIN, 0});
            next = std::min(next, c.until);
        }
        int timeoutMs = -1;
        if (!parked.empty())
            timeoutMs = static_cast<int>(std::clamp<long long>(
                std::chrono::duration_cast<std::chrono::milliseconds>(next - Clock::now()).count() +
                    1,
                0, 1000));
        if (::poll(p.data(), p.size(), timeoutMs) < 0 && errno != EINTR)
            break;
        if (p[1].revents) {
            char drained[64];
            while (::read(wake_[0], drained, sizeof drained) > 0) {
            }
        }
        if (stopping_)
            break;
        const auto now = Clock::now();
        kept.clear();
        for (std::size_t i = 0; i < parked.size(); ++i) {
            Parked& c = parked[i];
            Step step = now >= c.until ? Step::Close : Step::Keep;
            if (p[i + 2].revents != 0)
                step = readParked(c, now);
            if (step == Step::Close) {
                closeConnection(c.fd);
            } else if (step == Step::Serve) {
                pool_->enqueue([this, fd = c.fd, head = std::move(c.head),
                                left = c.left]() mutable { serve(fd, std::move(head), left); });
            } else {
                kept.push_back(std::move(c));
            }
        }
        parked.swap(kept);
        if (p[0].revents & POLLIN)
            acceptOne(parked);
    }
    for (const Parked& c : parked)
        closeConnection(c.fd);
}

BoundedServer::Step BoundedServer::readParked(Parked& c, Clock::time_point now) {
    for (;;) {
        char tmp[16384];
        const ssize_t n = ::recv(c.fd, tmp, sizeof tmp, MSG_DONTWAIT);
        if (n < 0 && errno == EINTR)
            continue;
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK))
            return now >= c.until ? Step::Close : Step::Keep;
        if (n <= 0)
            return Step::Close; // the client closed, or the connection failed
        if (c.lingering) {      // read and dropped
            c.discarded += static_cast<std::size_t>(n);
            if (c.discarded >= kLingerBytes)
                return Step::Close;
            continue;
        }
        if (c.head.empty()) // its first byte: the head deadline runs
            c.until = now + L::kHeadDeadline;
        const std::size_t from = c.head.size() < 2 ? 0 : c.head.size() - 2;
        c.head.append(tmp, static_cast<std::size_t>(n));
        if (headComplete(c.head, from))
            return Step::Serve;
    }
}

void BoundedServer::closeConnection(int fd) {
    std::lock_guard lock(mutex_);
    open_.erase(fd);
    ::close(fd);
}

void BoundedServer::park(Parked c) {
    {
        std::lock_guard lock(mutex_);
        handedOver_.push_back(std::move(c));
    }
    [[maybe_unused]] const auto n = ::write(wake_[1], "p", 1); // a full pipe: already woken
}

void BoundedServer::acceptOne(std::vector<Parked>& parked) {
    const int fd = ::accept4(listenFd_, nullptr, nullptr, SOCK_CLOEXEC);
    if (fd < 0) {
        if (errno == EMFILE || errno == ENFILE) // out of descriptors: let the others finish
            ::poll(nullptr, 0, 10);
        return;
    }
    std::lock_guard lock(mutex_);
    if (open_.size() >= static_cast<std::size_t>(L::kMaxConnections)) {
        static const std::string busy =
            "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
            "Content-Length: 52\r\nConnection: close\r\nRetry-After: 5\r\n\r\n"
            "{\"error\": \"too many connections; try again shortly\"}";
        [[maybe_unused]] auto n = ::send(fd, busy.data(), busy.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
        ::close(fd);
        return;
    }
    open_.insert(fd);
    parked.push_back(Parked::awaiting(fd, L::kKeepAliveRequests));
}

void BoundedServer::serve(int fd, std::string received, int left) noexcept {
    std::optional<Parked> after; // where the connection goes when this worker is done with it
    try {
        Connection conn(fd, std::move(received));
        tConnection = &conn;
        while (left > 0 && !stopping_) {
            if (!conn.hasCompleteHead()) { // the next head (or its beginning) is the acceptor's
                after = Parked::awaiting(fd, left, conn.unread());
                break;
            }
            conn.beginRequest();
            bool closed = false;
            // Range headers are ignored (the whole content is sent, as HTTP allows): httplib
            // 0.11 bounds neither their number nor their offsets.
            const bool ok = process_request(conn, left == 1 || stopping_, closed,
                                            [](httplib::Request& req) { req.ranges.clear(); });
            --left;
            if (!ok || closed || conn.mustClose()) {
                if (ok && conn.mustClose()) {
                    conn.finishSending();
                    after = Parked::draining(fd);
                }
                break;
            }
        }
    } catch (...) { // nothing leaves a worker; the connection just ends
        after.reset();
    }
    tConnection = nullptr;
    if (after && !stopping_)
        return park(std::move(*after));
    closeConnection(fd);
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
