#pragma once
// Private to http/: httplib's request parsing and routing over connections this server accepts
// and bounds itself (HttpLimits), and the admission check every request passes before its body
// is read.
#include "http_util.hpp"

#include "slicestation/core/result.hpp"
#include "slicestation/daemon/http/http_api.hpp"

#include <httplib.h>

#include <array>
#include <atomic>
#include <chrono>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

namespace slicestation::daemon::http {

/// httplib 0.11's own loop bounds neither the size of a request head or chunked body nor the
/// total time a client may take to send them, and serves a fixed pool from an unbounded queue:
/// this server accepts connections itself, at most HttpLimits::kMaxConnections open (past them
/// 503 and closed). Its acceptor thread reads each request head until it is complete and only
/// then hands the connection to one of kWorkers workers, which serves it through a Connection
/// and gives it back between requests: a worker is held by a request being answered (and an
/// event stream), never by a client that is slow to send its head, idles or was refused.
class BoundedServer final : public httplib::Server {
public:
    ~BoundedServer() override { stopServing(); }
    /// Binds (port 0: any free port). \return the port bound; IoError when it cannot be.
    core::Result<int> bindTo(const std::string& host, int port);
    core::Result<void> startServing();
    /// Ends every connection and joins every thread; idempotent.
    void stopServing() noexcept;

private:
    using Clock = std::chrono::steady_clock;
    static constexpr auto kLinger = std::chrono::seconds(1);
    static constexpr std::size_t kLingerBytes = 4u << 20;
    /// A connection no worker serves: either waiting for its next request's head (read here
    /// until complete, then handed to a worker with it) or, after an answer whose request was
    /// not read to its end, drained until the client closes, kLinger passes or kLingerBytes
    /// came, then closed. Both are the acceptor's, so a client that sends slowly, idles
    /// between requests or was refused holds no worker.
    struct Parked {
        int fd;
        Clock::time_point until; ///< when it is given up (idle, head deadline, linger)
        bool lingering = false;
        int left = 0;              ///< requests it may still make
        std::size_t discarded = 0; ///< lingering: bytes read and dropped
        std::string head;          ///< awaiting: the head so far (its deadline runs once begun)

        /// Waiting for a request head, `head` of it come already.
        static Parked awaiting(int fd, int left, std::string head = {}) {
            const auto limit = head.empty() ? HttpLimits::kIdle : HttpLimits::kHeadDeadline;
            return Parked{fd, Clock::now() + limit, false, left, 0, std::move(head)};
        }
        static Parked draining(int fd) {
            return Parked{fd, Clock::now() + kLinger, true, 0, 0, {}};
        }
    };
    enum class Step { Keep, Serve, Close };

    void acceptLoop();
    void acceptOne(std::vector<Parked>& parked);
    void serve(int fd, std::string received, int left) noexcept;
    /// Reads what `c` has to read: a head's bytes, kept, or a lingering one's, dropped.
    /// \return what to do with it now.
    static Step readParked(Parked& c, Clock::time_point now);
    void park(Parked p);
    void closeConnection(int fd);

    int listenFd_ = -1;
    std::array<int, 2> wake_{-1, -1};
    std::atomic<bool> stopping_{false};
    std::unique_ptr<httplib::ThreadPool> pool_;
    std::thread acceptor_;
    std::mutex mutex_;
    std::set<int> open_;             ///< every accepted connection until it is closed
    std::vector<Parked> handedOver_; ///< from workers to the acceptor (under mutex_)
};

/// Installs the admission check, run after a request's head and before its body: POSTs need
/// the token (`authorised`) and a Content-Length within kMaxBody (else 401, 411, 413); other
/// methods than GET, HEAD and POST get 405; a GET or HEAD with a body 400. A refused request's
/// connection closes after the answer.
void installAdmission(httplib::Server& server, const Authoriser& authorised);

} // namespace slicestation::daemon::http
