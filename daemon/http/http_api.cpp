#include "slicestation/daemon/http/http_api.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/station/autofocus.hpp"
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/http/web_page.hpp"

#include <httplib.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <fcntl.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <functional>
#include <limits>
#include <mutex>
#include <set>
#include <thread>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

using Clock = std::chrono::steady_clock;
using L = HttpLimits;
constexpr std::size_t kMaxBody = L::kMaxBody; // a plan of thousands of sections fits in far less
static_assert(L::kWorkers > L::kMaxEventStreams + 32, "room besides the event streams");

int httpStatus(const core::Error& e) {
    switch (e.code) {
    case ErrorCode::InvalidArgument:
    case ErrorCode::OutOfRange:
    case ErrorCode::Unsupported: return 400;
    case ErrorCode::NotFound: return 404;
    default: return 500;
    }
}

/// Never throws on what it sends: bytes that are not UTF-8 become U+FFFD.
std::string dumpJson(const nlohmann::json& j) {
    return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

void sendJson(httplib::Response& res, const nlohmann::json& j, int status = 200) {
    res.status = status;
    res.set_content(dumpJson(j), "application/json");
}

/// Something from the request, for a message: quoted and cut to 40 bytes.
std::string echo(const std::string& s) {
    return "\"" + (s.size() > 40 ? s.substr(0, 40) + "..." : s) + "\"";
}

void sendError(httplib::Response& res, int status, const std::string& message) {
    sendJson(res, {{"error", message}}, status);
}

void sendError(httplib::Response& res, const core::Error& e) { sendError(res, httpStatus(e), e.message); }

/// A control request refused: 404 no such record, 409 not in a state for it, 400 a bad value.
int controlStatus(const core::Error& e) {
    switch (e.code) {
    case ErrorCode::NotFound: return 404;
    case ErrorCode::InvalidArgument: return 409;
    case ErrorCode::OutOfRange:
    case ErrorCode::Unsupported: return 400;
    default: return 500;
    }
}

/// The numeric id in path capture 1; 400 for anything else (no path reaches a file).
std::optional<std::int64_t> idParam(const httplib::Request& req, httplib::Response& res) {
    const std::string s = req.matches.size() > 1 ? std::string(req.matches[1]) : std::string();
    std::int64_t v = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc() || p != s.data() + s.size() || v <= 0) {
        sendError(res, 400, "bad id " + echo(s));
        return std::nullopt;
    }
    return v;
}

/// An integer query parameter within [lo, hi]; `fallback` when absent; nullopt (400 sent) when bad.
std::optional<int> intQuery(const httplib::Request& req, httplib::Response& res, const char* name, int lo, int hi,
                            std::optional<int> fallback) {
    if (!req.has_param(name)) {
        if (!fallback) sendError(res, 400, std::string("missing query parameter ") + name);
        return fallback;
    }
    const std::string s = req.get_param_value(name);
    int v = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc() || p != s.data() + s.size() || v < lo || v > hi) {
        sendError(res, 400, std::string(name) + ": expected an integer " + std::to_string(lo) + ".." +
                                std::to_string(hi) + ", got " + echo(s));
        return std::nullopt;
    }
    return v;
}

/// A file the journal refers to, resolved inside the state directory; nullopt when it would
/// leave it (a damaged journal must not make the API serve arbitrary files).
std::optional<std::filesystem::path> storedFile(const std::filesystem::path& stateDir, const std::string& rel) {
    std::error_code ec;
    const auto root = std::filesystem::weakly_canonical(stateDir, ec);
    if (ec || rel.empty()) return std::nullopt;
    const auto full = std::filesystem::weakly_canonical(stateDir / rel, ec);
    if (ec) return std::nullopt;
    const auto r = full.lexically_relative(root);
    if (r.empty() || *r.begin() == "..") return std::nullopt;
    return full;
}

/// 8-bit for display: 16-bit images stretched between their 0.5 and 99.5 percentiles.
cv::Mat displayable(const cv::Mat& m) {
    if (m.depth() == CV_8U) return m;
    cv::Mat grey = m.channels() == 1 ? m : cv::Mat();
    if (grey.empty()) cv::cvtColor(m, grey, m.channels() == 4 ? cv::COLOR_BGRA2GRAY : cv::COLOR_BGR2GRAY);
    cv::Mat f;
    grey.convertTo(f, CV_32F);
    std::vector<float> sample;
    sample.reserve(f.total() / 7 + 1);
    for (std::size_t i = 0; i < f.total(); i += 7) sample.push_back(f.at<float>(static_cast<int>(i)));
    if (sample.empty()) return cv::Mat();
    auto at = [&](double q) {
        auto it = sample.begin() + static_cast<std::ptrdiff_t>(q * static_cast<double>(sample.size() - 1));
        std::nth_element(sample.begin(), it, sample.end());
        return static_cast<double>(*it);
    };
    const double lo = at(0.005), hi = std::max(at(0.995), lo + 1);
    cv::Mat out;
    f.convertTo(out, CV_8U, 255.0 / (hi - lo), -lo * 255.0 / (hi - lo));
    return out;
}

/// Scales to `width` (never up) and encodes; `ext` ".jpg" or ".png".
void sendImage(httplib::Response& res, const cv::Mat& image, int width, const std::string& ext) {
    cv::Mat m = displayable(image);
    if (m.empty()) return sendError(res, 500, "image cannot be shown");
    if (width < m.cols) {
        cv::Mat small;
        cv::resize(m, small, cv::Size(width, std::max(1, static_cast<int>(std::lround(m.rows * double(width) / m.cols)))),
                   0, 0, cv::INTER_AREA);
        m = small;
    }
    std::vector<uchar> buf;
    const std::vector<int> params = ext == ".jpg" ? std::vector<int>{cv::IMWRITE_JPEG_QUALITY, 85} : std::vector<int>{};
    if (!cv::imencode(ext, m, buf, params)) return sendError(res, 500, "cannot encode the image");
    res.set_header("Cache-Control", "no-store");
    res.set_content(std::string(buf.begin(), buf.end()), ext == ".jpg" ? "image/jpeg" : "image/png");
}

/// A stored image (a journal path, checked to lie inside the state directory), scaled and encoded.
void sendStoredImage(httplib::Response& res, const std::filesystem::path& stateDir, const std::string& rel,
                     int width, const std::string& ext) {
    auto file = storedFile(stateDir, rel);
    if (!file) return sendError(res, 500, "stored path \"" + rel + "\" is outside the state directory");
    auto img = core::readImage(*file);
    if (!img) return sendError(res, 500, img.error().message);
    sendImage(res, *img, width, ext);
}

/// One client connection, as the httplib::Stream the request parser reads: every read is
/// bounded in bytes (the head to kMaxHead, the body to what the admission allowed) and in time
/// (a deadline per request, not per byte, so a client trickling bytes is cut off all the same).
/// Writes give up after kWriteStall without progress. Used on the connection's worker only.
class Connection final : public httplib::Stream {
public:
    explicit Connection(int fd) : fd_(fd) {}

    /// Waits up to `idle` for the next request to begin. False: closed, idle, or refused.
    bool awaitRequest(Clock::duration idle) {
        if (mustClose_) return false;
        if (pos_ < len_) return true;
        return waitFor(POLLIN, Clock::now() + idle) && fill() > 0;
    }
    /// A new request: its head may take kMaxHead bytes and kHeadDeadline.
    void beginRequest() {
        used_ = 0;
        limit_ = L::kMaxHead;
        deadline_ = Clock::now() + L::kHeadDeadline;
        eofAtLimit_ = false;
    }
    /// After the head: the body is `length` bytes, within kBodyDeadline. nullopt: no body at all
    /// (reads end there, as HTTP says of a request without Content-Length).
    void allowBody(std::optional<std::size_t> length) {
        limit_ = used_ + length.value_or(0);
        eofAtLimit_ = !length;
        deadline_ = Clock::now() + L::kBodyDeadline;
    }
    /// The connection ends after this response (its body was not read, or it was refused).
    void closeAfterResponse() { mustClose_ = true; }
    bool mustClose() const { return mustClose_; }
    /// The client has gone (an event stream's client never sends anything after its request).
    bool peerGone() const {
        pollfd p{fd_, POLLRDHUP, 0};
        return ::poll(&p, 1, 0) > 0 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR)) != 0;
    }
    /// Before closing a connection whose request body was left unread: the answer is sent
    /// (FIN) and what the client still sends is discarded for a moment, so that the close does
    /// not reset the connection before the client has read the answer.
    void lingerBeforeClose() {
        ::shutdown(fd_, SHUT_WR);
        const auto until = Clock::now() + std::chrono::seconds(1);
        std::size_t discarded = 0;
        while (discarded < (4u << 20) && waitFor(POLLIN, until)) {
            char tmp[16384];
            const ssize_t n = ::recv(fd_, tmp, sizeof tmp, 0);
            if (n <= 0) break;
            discarded += static_cast<std::size_t>(n);
        }
    }

    bool is_readable() const override { return pos_ < len_ || waitFor(POLLIN, deadline_); }
    bool is_writable() const override { return waitFor(POLLOUT, Clock::now() + L::kWriteStall); }
    ssize_t read(char* ptr, std::size_t size) override {
        if (used_ >= limit_) {
            if (eofAtLimit_) return 0;
            mustClose_ = true; // over the limit: the request is cut off here
            return -1;
        }
        size = std::min(size, limit_ - used_);
        if (pos_ == len_) {
            if (!waitFor(POLLIN, deadline_)) {
                mustClose_ = true; // too slow
                return -1;
            }
            const ssize_t n = fill();
            if (n <= 0) {
                mustClose_ = true;
                return n;
            }
        }
        const std::size_t n = std::min(size, len_ - pos_);
        std::memcpy(ptr, buf_.data() + pos_, n);
        pos_ += n;
        used_ += n;
        return static_cast<ssize_t>(n);
    }
    ssize_t write(const char* ptr, std::size_t size) override {
        std::size_t done = 0;
        while (done < size) {
            if (!waitFor(POLLOUT, Clock::now() + L::kWriteStall)) return -1;
            const ssize_t n = ::send(fd_, ptr + done, size - done, MSG_NOSIGNAL | MSG_DONTWAIT);
            if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) continue;
            if (n <= 0) return -1;
            done += static_cast<std::size_t>(n);
        }
        return static_cast<ssize_t>(size);
    }
    void get_remote_ip_and_port(std::string& ip, int& port) const override { address(false, ip, port); }
    void get_local_ip_and_port(std::string& ip, int& port) const override { address(true, ip, port); }
    int socket() const override { return fd_; }

private:
    bool waitFor(short events, Clock::time_point until) const {
        for (;;) {
            const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now()).count();
            if (left <= 0) return false;
            pollfd p{fd_, events, 0};
            const int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(left, 1000 * 60)));
            if (r > 0) return true; // ready, or an error the next call reports
            if (r < 0 && errno != EINTR) return false;
        }
    }
    ssize_t fill() {
        for (;;) {
            const ssize_t n = ::recv(fd_, buf_.data(), buf_.size(), 0);
            if (n < 0 && errno == EINTR) continue;
            pos_ = 0;
            len_ = n > 0 ? static_cast<std::size_t>(n) : 0;
            return n;
        }
    }
    void address(bool local, std::string& ip, int& port) const {
        sockaddr_storage a{};
        socklen_t n = sizeof a;
        const int r = local ? ::getsockname(fd_, reinterpret_cast<sockaddr*>(&a), &n)
                            : ::getpeername(fd_, reinterpret_cast<sockaddr*>(&a), &n);
        std::array<char, NI_MAXHOST> host{};
        std::array<char, NI_MAXSERV> serv{};
        if (r != 0 || ::getnameinfo(reinterpret_cast<sockaddr*>(&a), n, host.data(), host.size(), serv.data(),
                                    serv.size(), NI_NUMERICHOST | NI_NUMERICSERV) != 0)
            return;
        ip = host.data();
        port = std::atoi(serv.data());
    }

    int fd_;
    std::array<char, 4096> buf_{};
    std::size_t pos_ = 0, len_ = 0;
    std::size_t used_ = 0, limit_ = L::kMaxHead;
    bool eofAtLimit_ = false;
    bool mustClose_ = false;
    Clock::time_point deadline_ = Clock::now() + L::kHeadDeadline;
};

/// The connection the calling worker serves (request handlers run on it).
thread_local Connection* tConnection = nullptr;

} // namespace

/// httplib's request parsing and routing, over connections this class accepts and bounds
/// itself: httplib 0.11's own loop bounds neither the size of a request head or chunked body
/// nor the total time a client may take to send them, and serves a fixed pool from an
/// unbounded queue.
class HttpApi::Server final : public httplib::Server {
public:
    ~Server() override { stopServing(); }

    core::Result<int> bindTo(const std::string& host, int port) {
        addrinfo hints{};
        hints.ai_family = AF_UNSPEC;
        hints.ai_socktype = SOCK_STREAM;
        hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
        addrinfo* found = nullptr;
        if (::getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &found) != 0 || !found)
            return makeError(ErrorCode::IoError, "HTTP: cannot resolve " + host);
        for (addrinfo* a = found; a && listenFd_ < 0; a = a->ai_next) {
            const int fd = ::socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
            if (fd < 0) continue;
            const int yes = 1;
            ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
            if (::bind(fd, a->ai_addr, a->ai_addrlen) == 0 && ::listen(fd, 64) == 0)
                listenFd_ = fd;
            else
                ::close(fd);
        }
        ::freeaddrinfo(found);
        if (listenFd_ < 0)
            return makeError(ErrorCode::IoError, "HTTP: cannot bind " + host + ":" + std::to_string(port) +
                                                     " (in use, or not an address of this machine)");
        sockaddr_storage a{};
        socklen_t n = sizeof a;
        ::getsockname(listenFd_, reinterpret_cast<sockaddr*>(&a), &n);
        int bound = 0;
        if (a.ss_family == AF_INET) bound = ntohs(reinterpret_cast<sockaddr_in*>(&a)->sin_port);
        if (a.ss_family == AF_INET6) bound = ntohs(reinterpret_cast<sockaddr_in6*>(&a)->sin6_port);
        return bound;
    }

    core::Result<void> startServing() {
        if (::pipe2(wake_.data(), O_CLOEXEC | O_NONBLOCK) != 0)
            return makeError(ErrorCode::IoError, "HTTP: cannot create a pipe");
        svr_sock_ = listenFd_; // httplib streams responses while this is valid
        pool_ = std::make_unique<httplib::ThreadPool>(static_cast<std::size_t>(L::kWorkers));
        acceptor_ = std::thread([this] { acceptLoop(); });
        return {};
    }

    void stopServing() noexcept {
        if (stopping_.exchange(true)) return;
        svr_sock_ = INVALID_SOCKET; // ends every streamed response at its next step
        if (wake_[1] >= 0) {
            [[maybe_unused]] const auto n = ::write(wake_[1], "x", 1);
        }
        if (acceptor_.joinable()) acceptor_.join();
        {
            std::lock_guard lock(mutex_);
            for (int fd : open_) ::shutdown(fd, SHUT_RDWR); // wakes every wait on them
        }
        if (pool_) pool_->shutdown();
        pool_.reset();
        for (int& fd : wake_)
            if (fd >= 0) ::close(std::exchange(fd, -1));
        if (listenFd_ >= 0) ::close(std::exchange(listenFd_, -1));
    }

private:
    void acceptLoop() {
        for (;;) {
            std::array<pollfd, 2> p{pollfd{listenFd_, POLLIN, 0}, pollfd{wake_[0], POLLIN, 0}};
            if (::poll(p.data(), p.size(), -1) < 0 && errno != EINTR) break;
            if (stopping_ || p[1].revents) break;
            if (!(p[0].revents & POLLIN)) continue;
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
                    [[maybe_unused]] auto n = ::send(fd, busy.data(), busy.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
                    ::close(fd);
                    continue;
                }
                open_.insert(fd);
            }
            pool_->enqueue([this, fd] { serve(fd); });
        }
    }

    void serve(int fd) noexcept {
        try {
            Connection conn(fd);
            tConnection = &conn;
            for (int left = L::kKeepAliveRequests; left > 0 && !stopping_; --left) {
                if (!conn.awaitRequest(L::kIdle)) break;
                conn.beginRequest();
                bool closed = false;
                // Range headers are ignored (the whole content is sent, as HTTP allows): httplib
                // 0.11 bounds neither their number nor their offsets.
                const bool ok = process_request(conn, left == 1 || stopping_, closed,
                                                [](httplib::Request& req) { req.ranges.clear(); });
                if (!ok || closed || conn.mustClose()) {
                    if (ok && conn.mustClose()) conn.lingerBeforeClose();
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

    int listenFd_ = -1;
    std::array<int, 2> wake_{-1, -1};
    std::atomic<bool> stopping_{false};
    std::unique_ptr<httplib::ThreadPool> pool_;
    std::thread acceptor_;
    std::mutex mutex_;
    std::set<int> open_;
};

namespace {

/// Admission, before httplib reads a body: POSTs need the token and a Content-Length within
/// kMaxBody; other methods carry no body. \return false when refused (the answer is in `res`
/// and the connection closes after it).
bool admit(const httplib::Request& req, httplib::Response& res, const std::function<bool(const httplib::Request&, httplib::Response&)>& authorised) {
    Connection* conn = tConnection;
    auto refuse = [&](int status, const std::string& message) {
        if (!message.empty()) sendError(res, status, message);
        res.set_header("Connection", "close");
        if (conn) conn->closeAfterResponse();
        return false;
    };
    std::optional<std::size_t> length;
    if (req.has_header("Content-Length")) {
        const std::string s = req.get_header_value("Content-Length");
        std::uint64_t v = 0;
        const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
        if (ec == std::errc::result_out_of_range) v = std::numeric_limits<std::uint64_t>::max();
        else if (ec != std::errc() || p != s.data() + s.size() || req.get_header_value_count("Content-Length") != 1)
            return refuse(400, "Content-Length: expected one number of bytes, got " + echo(s));
        length = static_cast<std::size_t>(std::min<std::uint64_t>(v, kMaxBody + 1));
    }
    const bool chunked = req.has_header("Transfer-Encoding");
    if (req.method == "POST") {
        if (!authorised(req, res)) return refuse(401, "");
        if (chunked)
            return refuse(411, "a request body needs a Content-Length (chunked bodies are not accepted)");
        if (length && *length > kMaxBody)
            return refuse(413, "request body over the limit of " + std::to_string(kMaxBody) + " bytes");
        if (conn) conn->allowBody(length);
        return true;
    }
    if (req.method != "GET" && req.method != "HEAD") {
        res.set_header("Allow", "GET, HEAD, POST");
        return refuse(405, "method " + echo(req.method) + " not allowed");
    }
    if (chunked || length.value_or(0) > 0) return refuse(400, "a " + req.method + " request has no body");
    if (conn) conn->allowBody(std::nullopt);
    return true;
}

} // namespace

/// Station events fanned out to every event-stream client. A client that does not keep up
/// loses its oldest events (counted), never slows the station: publishing only takes a mutex.
struct HttpApi::EventHub {
    struct Client {
        std::mutex mutex;
        std::condition_variable cv;
        std::deque<std::string> queue;
        bool closed = false;
        bool greeted = false;
        std::uint64_t dropped = 0;
    };
    static constexpr std::size_t kMaxQueued = 256;
    std::mutex mutex;
    std::vector<std::weak_ptr<Client>> clients;
    bool closed = false;

    void publish(const std::string& message) {
        std::lock_guard lock(mutex);
        std::erase_if(clients, [](const auto& w) { return w.expired(); });
        for (auto& w : clients)
            if (auto c = w.lock()) {
                std::lock_guard cl(c->mutex);
                if (c->queue.size() >= kMaxQueued) {
                    c->queue.pop_front();
                    ++c->dropped;
                }
                c->queue.push_back(message);
                c->cv.notify_one();
            }
    }
    /// A new client; null when kMaxEventStreams are open (a client is open while its
    /// response lives).
    std::shared_ptr<Client> subscribe() {
        std::lock_guard lock(mutex);
        std::erase_if(clients, [](const auto& w) { return w.expired(); });
        if (clients.size() >= static_cast<std::size_t>(L::kMaxEventStreams)) return nullptr;
        auto c = std::make_shared<Client>();
        c->closed = closed;
        clients.push_back(c);
        return c;
    }
    void close() {
        std::lock_guard lock(mutex);
        closed = true;
        for (auto& w : clients)
            if (auto c = w.lock()) {
                std::lock_guard cl(c->mutex);
                c->closed = true;
                c->cv.notify_all();
            }
    }
};

core::Result<std::unique_ptr<HttpApi>> HttpApi::start(Station& station, const std::string& bind, int port,
                                                      std::string token) {
    std::unique_ptr<HttpApi> api(new HttpApi());
    api->server_ = std::make_unique<Server>();
    auto& srv = *api->server_;
    // The connections, their timeouts and sizes are bounded by Server and Connection (HttpLimits);
    // these only make httplib's own checks and Keep-Alive header agree.
    srv.set_payload_max_length(kMaxBody);
    srv.set_keep_alive_max_count(static_cast<std::size_t>(L::kKeepAliveRequests));
    srv.set_keep_alive_timeout(std::chrono::duration_cast<std::chrono::seconds>(L::kIdle).count());

    // Control requests need the bearer token; without a configured token they are refused.
    auto authorised = [token](const httplib::Request& req, httplib::Response& res) {
        if (token.empty()) {
            sendError(res, 401, "control is disabled: no daemon.token configured");
            return false;
        }
        const std::string expected = "Bearer " + token;
        const std::string got = req.get_header_value("Authorization");
        // Constant-time comparison: the token is a secret.
        bool same = got.size() == expected.size();
        unsigned char diff = 0;
        for (std::size_t i = 0; i < expected.size(); ++i)
            diff |= static_cast<unsigned char>(expected[i] ^ (i < got.size() ? got[i] : 0));
        if (!same || diff != 0) {
            res.set_header("WWW-Authenticate", "Bearer");
            sendError(res, 401, "missing or wrong bearer token");
            return false;
        }
        return true;
    };
    Station* st = &station;
    // Before any body is read (httplib runs this after the head, before reading content).
    srv.set_pre_routing_handler([authorised](const httplib::Request& req, httplib::Response& res) {
        return admit(req, res, authorised) ? httplib::Server::HandlerResponse::Unhandled
                                           : httplib::Server::HandlerResponse::Handled;
    });
    // A client that asks before sending its body is told the same, before it sends it.
    srv.set_expect_100_continue_handler([authorised](const httplib::Request& req, httplib::Response& res) {
        return admit(req, res, authorised) ? 100 : res.status;
    });

    // The page: self-contained, and the browser is told to load nothing from elsewhere.
    srv.Get("/", [](const httplib::Request&, httplib::Response& res) {
        res.set_header("Content-Security-Policy",
                       "default-src 'self'; img-src 'self' blob:; style-src 'unsafe-inline'; "
                       "script-src 'unsafe-inline'; connect-src 'self'");
        res.set_header("X-Content-Type-Options", "nosniff");
        res.set_header("Cache-Control", "no-cache");
        const auto page = webPage();
        res.set_content(page.data(), page.size(), "text/html; charset=utf-8");
    });
    srv.Get("/api/status", [st](const httplib::Request&, httplib::Response& res) { sendJson(res, st->status()); });
    srv.Get("/api/runs", [st](const httplib::Request&, httplib::Response& res) {
        auto runs = st->journal().runs();
        if (!runs) return sendError(res, runs.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& r : *runs) j.push_back(toJson(r));
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+))", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        auto r = st->journal().run(*id);
        if (!r) return sendError(res, r.error());
        nlohmann::json j = toJson(*r);
        j["plan"] = r->plan;
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+)/sections)", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        if (auto r = st->journal().run(*id); !r) return sendError(res, r.error());
        auto secs = st->journal().sections(*id);
        if (!secs) return sendError(res, secs.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& s : *secs) j.push_back(toJson(s));
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+)/export)", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        const std::string format = req.has_param("format") ? req.get_param_value("format") : "json";
        auto out = st->exportRun(*id, format);
        if (!out) return sendError(res, out.error());
        res.set_content(*out, format == "csv" ? "text/csv" : "application/json");
    });
    srv.Get(R"(/api/sections/([^/]+))", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        auto d = st->sectionDetail(*id);
        if (!d) return sendError(res, d.error());
        sendJson(res, *d);
    });
    srv.Get("/api/alerts", [st](const httplib::Request& req, httplib::Response& res) {
        const bool open = req.has_param("open") && req.get_param_value("open") != "0";
        auto a = st->journal().alerts(open);
        if (!a) return sendError(res, a.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& x : *a) j.push_back(toJson(x));
        sendJson(res, j);
    });

    // Server-Sent Events: every station event as "event: TYPE" + "data: JSON".
    api->events_ = std::make_shared<EventHub>();
    {
        std::weak_ptr<EventHub> hub = api->events_;
        station.notifier().addListener([hub](const StationEvent& e) {
            if (auto h = hub.lock()) h->publish("event: " + e.type + "\ndata: " + dumpJson(e.data) + "\n\n");
        });
    }
    srv.Get("/api/events", [hub = api->events_](const httplib::Request&, httplib::Response& res) {
        auto client = hub->subscribe();
        Connection* conn = tConnection;
        if (!client || !conn) {
            res.set_header("Retry-After", "5");
            res.set_header("Connection", "close");
            if (conn) conn->closeAfterResponse();
            return sendError(res, 503,
                             "too many event streams: " + std::to_string(L::kMaxEventStreams) +
                                 " are open; try again later");
        }
        res.set_header("Cache-Control", "no-cache");
        res.set_header("X-Accel-Buffering", "no");
        res.set_chunked_content_provider(
            "text/event-stream",
            [client, conn](std::size_t, httplib::DataSink& sink) {
                std::string out;
                {
                    std::unique_lock lock(client->mutex);
                    if (!client->greeted) {
                        client->greeted = true;
                        out = "retry: 3000\n: connected\n\n";
                    } else {
                        // Up to 15 s for events; a client that has gone frees its place within 0.5 s.
                        const auto keepalive = Clock::now() + std::chrono::seconds(15);
                        while (!client->cv.wait_for(lock, std::chrono::milliseconds(500),
                                                    [&] { return !client->queue.empty() || client->closed; }) &&
                               Clock::now() < keepalive) {
                            lock.unlock();
                            const bool gone = conn->peerGone();
                            lock.lock();
                            if (gone) return false;
                        }
                        if (client->closed) return false;
                        if (client->dropped > 0) {
                            out += "event: events_dropped\ndata: {\"count\": " + std::to_string(client->dropped) +
                                   "}\n\n";
                            client->dropped = 0;
                        }
                        while (!client->queue.empty()) {
                            out += client->queue.front();
                            client->queue.pop_front();
                        }
                        if (out.empty()) out = ": keepalive\n\n";
                    }
                }
                return sink.write(out.data(), out.size());
            },
            [client](bool) {
                std::lock_guard lock(client->mutex);
                client->closed = true;
            });
    });

    // Images: the live view, a section's image and its overlay, scaled to ?width= (16..4096).
    srv.Get("/api/live.jpg", [st](const httplib::Request& req, httplib::Response& res) {
        auto width = intQuery(req, res, "width", 16, 4096, 1024);
        if (!width) return;
        auto frame = st->liveFrame();
        if (!frame) return sendError(res, 404, "no frame yet");
        sendImage(res, frameToMat(*frame), *width, ".jpg");
    });
    // A section's latest capture and its registration; with `registered`, a section not
    // registered yet is a 404.
    auto latest = [st](std::int64_t sectionId, httplib::Response& res, bool registered)
        -> std::optional<std::pair<CaptureRecord, std::optional<RegistrationRecord>>> {
        auto sec = st->journal().section(sectionId);
        if (!sec) {
            sendError(res, sec.error());
            return std::nullopt;
        }
        auto caps = st->journal().captures(sectionId);
        if (!caps || caps->empty()) {
            sendError(res, 404, "section " + std::to_string(sectionId) + " has no capture yet");
            return std::nullopt;
        }
        std::optional<RegistrationRecord> reg;
        if (auto regs = st->journal().registrations(sectionId))
            for (const auto& r : *regs)
                if (r.captureId == caps->back().id) reg = r;
        if (registered && !reg) {
            sendError(res, 404, "section " + std::to_string(sectionId) + " is not registered yet");
            return std::nullopt;
        }
        return std::make_pair(caps->back(), reg);
    };
    // A section's latest image, or its overlay once registered, scaled to ?width=.
    auto storedImageRoute = [&srv, st, latest](const char* pattern, bool overlay) {
        srv.Get(pattern, [st, latest, overlay](const httplib::Request& req, httplib::Response& res) {
            auto id = idParam(req, res);
            if (!id) return;
            auto width = intQuery(req, res, "width", 16, 4096, 1024);
            if (!width) return;
            auto l = latest(*id, res, overlay);
            if (!l) return;
            if (overlay)
                sendStoredImage(res, st->stateDir(), l->second->overlayPath, *width, ".png");
            else
                sendStoredImage(res, st->stateDir(), l->first.imagePath, *width, ".jpg");
        });
    };
    storedImageRoute(R"(/api/sections/([^/]+)/image\.jpg)", false);
    storedImageRoute(R"(/api/sections/([^/]+)/overlay\.png)", true);
    // The atlas region at a pixel of the section's latest capture (full resolution).
    struct LabelCache {
        std::mutex mutex;
        std::string path;
        cv::Mat labels;
    };
    auto cache = std::make_shared<LabelCache>();
    srv.Get(R"(/api/sections/([^/]+)/region)", [st, latest, cache](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        auto x = intQuery(req, res, "x", 0, 1 << 20, std::nullopt);
        if (!x) return;
        auto y = intQuery(req, res, "y", 0, 1 << 20, std::nullopt);
        if (!y) return;
        // ?of_width=W: x, y are pixels of the image shown scaled to width W (the page's overlay).
        auto ofWidth = intQuery(req, res, "of_width", 1, 1 << 20, 0);
        if (!ofWidth) return;
        auto l = latest(*id, res, true);
        if (!l) return;
        auto file = storedFile(st->stateDir(), l->second->labelsPath);
        if (!file) return sendError(res, 500, "stored labels path is outside the state directory");
        std::int32_t region = 0;
        {
            std::lock_guard lock(cache->mutex);
            if (cache->path != file->string()) {
                auto img = core::readImage(*file);
                if (!img || img->type() != CV_32SC1) return sendError(res, 500, "labels unreadable");
                cache->labels = *img;
                cache->path = file->string();
            }
            // In double, and checked before the cast: scaled, x and y may lie far beyond int.
            double fx = *x, fy = *y;
            if (*ofWidth > 0) {
                const double f = static_cast<double>(cache->labels.cols) / *ofWidth;
                fx = std::floor((fx + 0.5) * f);
                fy = std::floor((fy + 0.5) * f);
            }
            if (!(fx >= 0 && fx < cache->labels.cols && fy >= 0 && fy < cache->labels.rows))
                return sendError(res, 400, "x, y: outside the " + std::to_string(cache->labels.cols) + "x" +
                                               std::to_string(cache->labels.rows) + " image");
            *x = static_cast<int>(fx);
            *y = static_cast<int>(fy);
            region = cache->labels.at<std::int32_t>(*y, *x);
        }
        nlohmann::json j{{"id", region}, {"x", *x}, {"y", *y}};
        if (region > 0)
            if (const StackRegion* r = findRegion(st->atlas(), static_cast<std::uint32_t>(region))) {
                j["name"] = r->name;
                j["acronym"] = r->acronym;
            }
        sendJson(res, j);
    });

    srv.Post("/api/runs", [st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res)) return;
        const std::string type = req.get_header_value("Content-Type");
        const bool json = type.find("json") != std::string::npos ||
                          (type.find("toml") == std::string::npos && !req.body.empty() &&
                           req.body[req.body.find_first_not_of(" \t\r\n") == std::string::npos
                                        ? 0
                                        : req.body.find_first_not_of(" \t\r\n")] == '{');
        auto doc = parseDocument(req.body, json ? DocumentFormat::Json : DocumentFormat::Toml, "plan");
        if (!doc) return sendError(res, 400, doc.error().message);
        auto id = st->submitPlan(*doc, "plan");
        if (!id) return sendError(res, 400, id.error().message);
        sendJson(res, {{"run_id", *id}}, 201);
    });
    auto control = [&srv, st, authorised](const char* pattern, auto action) {
        srv.Post(pattern, [st, authorised, action](const httplib::Request& req, httplib::Response& res) {
            if (!authorised(req, res)) return;
            auto id = idParam(req, res);
            if (!id) return;
            core::Result<void> r = action(*st, *id);
            if (!r) return sendError(res, controlStatus(r.error()), r.error().message);
            sendJson(res, {{"ok", true}});
        });
    };
    control(R"(/api/runs/([^/]+)/pause)", [](Station& s, std::int64_t id) { return s.scanner().pause(id); });
    srv.Post(R"(/api/runs/([^/]+)/resume)", [st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res)) return;
        auto id = idParam(req, res);
        if (!id) return;
        bool resetAlarm = false;
        if (!req.body.empty()) {
            auto j = nlohmann::json::parse(req.body, nullptr, false);
            if (j.is_discarded() || !j.is_object() || (j.contains("reset_stage_alarm") && !j["reset_stage_alarm"].is_boolean()))
                return sendError(res, 400, "body: expected {\"reset_stage_alarm\": true | false}");
            resetAlarm = j.value("reset_stage_alarm", false);
        }
        auto r = st->scanner().resume(*id, resetAlarm);
        if (!r) return sendError(res, controlStatus(r.error()), r.error().message);
        sendJson(res, {{"ok", true}});
    });
    control(R"(/api/runs/([^/]+)/cancel)", [](Station& s, std::int64_t id) { return s.scanner().cancel(id); });
    control(R"(/api/sections/([^/]+)/rescan)", [](Station& s, std::int64_t id) { return s.requestRescan(id); });
    srv.Post(R"(/api/alerts/([^/]+)/ack)", [st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res)) return;
        auto id = idParam(req, res);
        if (!id) return;
        std::string action = "accept";
        if (!req.body.empty()) {
            auto j = nlohmann::json::parse(req.body, nullptr, false);
            if (j.is_discarded() || !j.is_object() || (j.contains("action") && !j["action"].is_string()))
                return sendError(res, 400, "body: expected {\"action\": \"rescan\" | \"accept\" | text}");
            action = j.value("action", action);
        }
        auto alert = st->journal().alert(*id);
        if (!alert) return sendError(res, alert.error());
        if (action == "rescan") {
            if (!alert->sectionId) return sendError(res, 409, "alert " + std::to_string(*id) + " concerns no section");
            if (auto r = st->requestRescan(*alert->sectionId); !r) return sendError(res, 409, r.error().message);
        }
        auto a = st->notifier().acknowledge(*id, action);
        if (!a) return sendError(res, a.error().code == ErrorCode::NotFound ? 404 : 409, a.error().message);
        sendJson(res, toJson(*a));
    });
    srv.set_error_handler([](const httplib::Request&, httplib::Response& res) {
        if (res.body.empty()) sendError(res, res.status, res.status == 404 ? "no such endpoint" : "request failed");
    });
    srv.set_exception_handler([](const httplib::Request&, httplib::Response& res, std::exception_ptr) {
        sendError(res, 500, "internal error");
    });

    if (port < 0 || port > 65535) return makeError(ErrorCode::InvalidArgument, "HTTP: port " + std::to_string(port));
    auto bound = srv.bindTo(bind, port);
    if (!bound) return bound.error();
    api->port_ = *bound;
    if (auto r = srv.startServing(); !r) return r.error();
    return api;
}

HttpApi::~HttpApi() { stop(); }

void HttpApi::stop() noexcept {
    if (events_) events_->close(); // event streams end at once, so the server can stop
    if (server_) server_->stopServing();
}

} // namespace slicestation::daemon
