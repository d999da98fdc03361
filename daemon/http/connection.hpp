#pragma once
// Private to http/: one client connection, bounded in bytes and time (HttpLimits).
#include "slicestation/daemon/http/http_api.hpp"

#include <httplib.h>

#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

namespace slicestation::daemon::http {

using Clock = std::chrono::steady_clock;
using L = HttpLimits;

/// A request head is all in `buffered` (searched from `from`): the blank line that ends it has
/// come (httplib skips a header line without its CR, so a head ends at "\r\n" after a line's
/// end), or kMaxHead bytes have, past which reading it refuses it.
inline bool headComplete(std::string_view buffered, std::size_t from = 0) {
    return buffered.size() >= L::kMaxHead ||
           buffered.find("\n\r\n", from) != std::string_view::npos;
}

/// One client connection, as the httplib::Stream the request parser reads: every read is
/// bounded in bytes (the head to kMaxHead, the body to what the admission allowed) and in time
/// (a deadline per request, not per byte, so a client trickling bytes is cut off all the same).
/// Writes give up after kWriteStall without progress. Used on the connection's worker only.
class Connection final : public httplib::Stream {
public:
    /// `received`: what the acceptor already read from the socket (a request head, and what
    /// came with it), read first.
    Connection(int fd, std::string received) : fd_(fd), buf_(std::move(received)) {
        len_ = buf_.size();
        if (buf_.size() < kChunk)
            buf_.resize(kChunk);
    }

    /// The next request's head is buffered here whole (headComplete).
    bool hasCompleteHead() const {
        return !mustClose_ && pos_ < len_ &&
               headComplete(std::string_view(buf_.data() + pos_, len_ - pos_));
    }
    /// What is buffered and not yet read (a pipelined request's beginning).
    std::string unread() const { return buf_.substr(pos_, len_ - pos_); }
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
    /// Before closing a connection whose request body may be left unread: the answer is sent
    /// (FIN), and the socket is then drained for a moment by BoundedServer's acceptor (not by
    /// this worker), so that the close does not reset the connection before the client has read
    /// the answer.
    void finishSending() { ::shutdown(fd_, SHUT_WR); }

    bool is_readable() const override { return pos_ < len_ || waitFor(POLLIN, deadline_); }
    bool is_writable() const override { return waitFor(POLLOUT, Clock::now() + L::kWriteStall); }
    ssize_t read(char* ptr, std::size_t size) override {
        if (used_ >= limit_) {
            if (eofAtLimit_)
                return 0;
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
            if (!waitFor(POLLOUT, Clock::now() + L::kWriteStall))
                return -1;
            const ssize_t n = ::send(fd_, ptr + done, size - done, MSG_NOSIGNAL | MSG_DONTWAIT);
            if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR))
                continue;
            if (n <= 0)
                return -1;
            done += static_cast<std::size_t>(n);
        }
        return static_cast<ssize_t>(size);
    }
    void get_remote_ip_and_port(std::string& ip, int& port) const override {
        address(false, ip, port);
    }
    void get_local_ip_and_port(std::string& ip, int& port) const override {
        address(true, ip, port);
    }
    int socket() const override { return fd_; }

private:
    bool waitFor(short events, Clock::time_point until) const {
        for (;;) {
            const auto left =
                std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now()).count();
            if (left <= 0)
                return false;
            pollfd p{fd_, events, 0};
            const int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(left, 1000 * 60)));
            if (r > 0)
                return true; // ready, or an error the next call reports
            if (r < 0 && errno != EINTR)
                return false;
        }
    }
    ssize_t fill() {
        for (;;) {
            if (buf_.size() > kChunk)
                buf_.resize(kChunk); // a long head, read: back to the usual chunk
            const ssize_t n = ::recv(fd_, buf_.data(), buf_.size(), 0);
            if (n < 0 && errno == EINTR)
                continue;
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
        if (r != 0 || ::getnameinfo(reinterpret_cast<sockaddr*>(&a), n, host.data(), host.size(),
                                    serv.data(), serv.size(), NI_NUMERICHOST | NI_NUMERICSERV) != 0)
            return;
        ip = host.data();
        port = std::atoi(serv.data());
    }

    int fd_;
    static constexpr std::size_t kChunk = 4096;
    std::string buf_;
    std::size_t pos_ = 0, len_ = 0;
    std::size_t used_ = 0, limit_ = L::kMaxHead;
    bool eofAtLimit_ = false;
    bool mustClose_ = false;
    Clock::time_point deadline_ = Clock::now() + L::kHeadDeadline;
};

/// The connection the calling worker serves (request handlers run on it); null elsewhere.
Connection* currentConnection() noexcept;

} // namespace slicestation::daemon::http
