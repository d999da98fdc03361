// Server-Sent Events: every station event as "event: TYPE" + "data: JSON".
#include "connection.hpp"
#include "routes.hpp"

#include <condition_variable>
#include <deque>
#include <mutex>
#include <vector>

namespace slicestation::daemon::http {

/// A client that does not keep up loses its oldest events (counted), never slows the station:
/// publishing only takes a mutex.
struct EventHub {
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
        if (clients.size() >= static_cast<std::size_t>(L::kMaxEventStreams))
            return nullptr;
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
void closeEventStreams(EventHub& hub) noexcept {
    hub.close();
}

namespace {

/// The next chunk of a client's stream: a greeting first, then the queued events (and how many
/// were dropped), or a keepalive comment after 15 s without any. False: the stream ends (the
/// client has gone, or the hub closed).
bool nextChunk(EventHub::Client& client, const Connection& conn, httplib::DataSink& sink) {
    std::string out;
    {
        std::unique_lock lock(client.mutex);
        if (!client.greeted) {
            client.greeted = true;
            out = "retry: 3000\n: connected\n\n";
        } else {
            // Up to 15 s for events; a client that has gone frees its place within 0.5 s.
            const auto keepalive = Clock::now() + std::chrono::seconds(15);
            while (!client.cv.wait_for(lock, std::chrono::milliseconds(500), [&] {
                return !client.queue.empty() || client.closed;
            }) && Clock::now() < keepalive) {
                lock.unlock();
                const bool gone = conn.peerGone();
                lock.lock();
                if (gone)
                    return false;
            }
            if (client.closed)
                return false;
            if (client.dropped > 0) {
                out +=
                    "event: events_dropped\ndata: {\"count\": " + std::to_string(client.dropped) +
                    "}\n\n";
                client.dropped = 0;
            }
            while (!client.queue.empty()) {
                out += client.queue.front();
                client.queue.pop_front();
            }
            if (out.empty())
                out = ": keepalive\n\n";
        }
    }
    return sink.write(out.data(), out.size());
}

} // namespace

std::shared_ptr<EventHub> addEventRoutes(httplib::Server& srv, StationApi& station) {
    auto hub = std::make_shared<EventHub>();
    station.addListener([weak = std::weak_ptr<EventHub>(hub)](const StationEvent& e) {
        if (auto h = weak.lock())
            h->publish("event: " + e.type + "\ndata: " + dumpJson(e.data) + "\n\n");
    });
    srv.Get("/api/events", [hub](const httplib::Request&, httplib::Response& res) {
        auto client = hub->subscribe();
        Connection* conn = currentConnection();
        if (!client || !conn) {
            res.set_header("Retry-After", "5");
            res.set_header("Connection", "close");
            if (conn)
                conn->closeAfterResponse();
            return sendError(res, 503,
                             "too many event streams: " + std::to_string(L::kMaxEventStreams) +
                                 " are open; try again later");
        }
        res.set_header("Cache-Control", "no-cache");
        res.set_header("X-Accel-Buffering", "no");
        res.set_chunked_content_provider(
            "text/event-stream",
            [client, conn](std::size_t, httplib::DataSink& sink) {
                return nextChunk(*client, *conn, sink);
            },
            [client](bool) {
                std::lock_guard lock(client->mutex);
                client->closed = true;
            });
    });
    return hub;
}

} // namespace slicestation::daemon::http
