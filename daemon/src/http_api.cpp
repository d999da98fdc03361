#include "slicestation/daemon/http_api.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/autofocus.hpp"
#include "slicestation/daemon/config_document.hpp"
#include "slicestation/daemon/web_page.hpp"

#include <httplib.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <mutex>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

constexpr std::size_t kMaxBody = 1 << 20; // a plan of thousands of sections fits in far less

int httpStatus(const core::Error& e) {
    switch (e.code) {
    case ErrorCode::InvalidArgument:
    case ErrorCode::OutOfRange:
    case ErrorCode::Unsupported: return 400;
    case ErrorCode::NotFound: return 404;
    default: return 500;
    }
}

void sendJson(httplib::Response& res, const nlohmann::json& j, int status = 200) {
    res.status = status;
    res.set_content(j.dump(), "application/json");
}

void sendError(httplib::Response& res, int status, const std::string& message) {
    sendJson(res, {{"error", message}}, status);
}

void sendError(httplib::Response& res, const core::Error& e) { sendError(res, httpStatus(e), e.message); }

/// The numeric id in path capture 1; 400 for anything else (no path reaches a file).
std::optional<std::int64_t> idParam(const httplib::Request& req, httplib::Response& res) {
    const std::string s = req.matches.size() > 1 ? std::string(req.matches[1]) : std::string();
    std::int64_t v = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc() || p != s.data() + s.size() || v <= 0) {
        sendError(res, 400, "bad id \"" + s + "\"");
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
                                std::to_string(hi) + ", got \"" + s + "\"");
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
    std::shared_ptr<Client> subscribe() {
        auto c = std::make_shared<Client>();
        std::lock_guard lock(mutex);
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
    api->server_ = std::make_unique<httplib::Server>();
    auto& srv = *api->server_;
    srv.set_payload_max_length(kMaxBody);
    // Event streams hold a thread each: room for a few browsers besides slicectl.
    srv.new_task_queue = [] { return new httplib::ThreadPool(16); };
    srv.set_read_timeout(10, 0);
    srv.set_write_timeout(10, 0);

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
            if (auto h = hub.lock()) h->publish("event: " + e.type + "\ndata: " + e.data.dump() + "\n\n");
        });
    }
    srv.Get("/api/events", [hub = api->events_](const httplib::Request&, httplib::Response& res) {
        auto client = hub->subscribe();
        res.set_header("Cache-Control", "no-cache");
        res.set_header("X-Accel-Buffering", "no");
        res.set_chunked_content_provider(
            "text/event-stream",
            [client](std::size_t, httplib::DataSink& sink) {
                std::string out;
                {
                    std::unique_lock lock(client->mutex);
                    if (!client->greeted) {
                        client->greeted = true;
                        out = "retry: 3000\n: connected\n\n";
                    } else {
                        client->cv.wait_for(lock, std::chrono::seconds(15),
                                            [&] { return !client->queue.empty() || client->closed; });
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
            if (*ofWidth > 0) {
                const double f = static_cast<double>(cache->labels.cols) / *ofWidth;
                *x = static_cast<int>(std::floor((*x + 0.5) * f));
                *y = static_cast<int>(std::floor((*y + 0.5) * f));
            }
            if (*x >= cache->labels.cols || *y >= cache->labels.rows)
                return sendError(res, 400, "x, y: outside the " + std::to_string(cache->labels.cols) + "x" +
                                               std::to_string(cache->labels.rows) + " image");
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
            if (!r) {
                const int code = r.error().code == ErrorCode::NotFound ? 404
                                 : r.error().code == ErrorCode::InvalidArgument ? 409
                                                                                 : 500;
                return sendError(res, code, r.error().message);
            }
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
        if (!r)
            return sendError(res, r.error().code == ErrorCode::NotFound ? 404
                                  : r.error().code == ErrorCode::InvalidArgument ? 409 : 500,
                             r.error().message);
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

    if (port == 0) {
        api->port_ = srv.bind_to_any_port(bind.c_str());
        if (api->port_ < 0) return makeError(ErrorCode::IoError, "HTTP: cannot bind " + bind);
    } else {
        if (!srv.bind_to_port(bind.c_str(), port))
            return makeError(ErrorCode::IoError, "HTTP: cannot bind " + bind + ":" + std::to_string(port) +
                                                     " (in use, or not an address of this machine)");
        api->port_ = port;
    }
    api->thread_ = std::thread([&srv] { srv.listen_after_bind(); });
    return api;
}

HttpApi::~HttpApi() { stop(); }

void HttpApi::stop() noexcept {
    if (events_) events_->close(); // event streams end at once, so the server can stop
    if (server_) server_->stop();
    if (thread_.joinable()) thread_.join();
}

} // namespace slicestation::daemon
