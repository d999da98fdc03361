#pragma once
// Private to http/: httplib's request parsing and routing over connections this server accepts
// and bounds itself (HttpLimits), and the admission check every request passes before its body
// is read.
#include "http_util.hpp"

#include "slicestation/core/result.hpp"

#include <httplib.h>

#include <array>
#include <atomic>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>

namespace slicestation::daemon::http {

/// httplib 0.11's own loop bounds neither the size of a request head or chunked body nor the
/// total time a client may take to send them, and serves a fixed pool from an unbounded queue:
/// this server accepts connections itself, at most HttpLimits::kMaxConnections open (past them
/// 503 and closed) and kWorkers served at once, each through a Connection.
class BoundedServer final : public httplib::Server {
public:
    ~BoundedServer() override { stopServing(); }
    /// Binds (port 0: any free port). \return the port bound; IoError when it cannot be.
    core::Result<int> bindTo(const std::string& host, int port);
    core::Result<void> startServing();
    /// Ends every connection and joins every thread; idempotent.
    void stopServing() noexcept;

private:
    void acceptLoop();
    void serve(int fd) noexcept;

    int listenFd_ = -1;
    std::array<int, 2> wake_{-1, -1};
    std::atomic<bool> stopping_{false};
    std::unique_ptr<httplib::ThreadPool> pool_;
    std::thread acceptor_;
    std::mutex mutex_;
    std::set<int> open_;
};

/// Installs the admission check, run after a request's head and before its body: POSTs need
/// the token (`authorised`) and a Content-Length within kMaxBody (else 401, 411, 413); other
/// methods than GET, HEAD and POST get 405; a GET or HEAD with a body 400. A refused request's
/// connection closes after the answer.
void installAdmission(httplib::Server& server, const Authoriser& authorised);

} // namespace slicestation::daemon::http
