#include "slicestation/daemon/alerts/alert_channels.hpp"

#include "alert_util.hpp"

#include "slicestation/core/unique_fd.hpp"
#include "slicestation/daemon/config/config_document.hpp"

#include <httplib.h>
#include <systemd/sd-journal.h>

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <sys/uio.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <deque>
#include <initializer_list>
#include <map>
#include <optional>
#include <string_view>
#include <thread>

extern char** environ; // NOLINT(readability-redundant-declaration): POSIX declares it nowhere

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using Clock = std::chrono::steady_clock;

// Webhook --------------------------------------------------------------------------------------

struct WebhookSink::Impl {
    WebhookSettings settings;
    ParsedUrl url;
    std::string station = hostName();
    std::mutex mutex;
    httplib::Client* current = nullptr; ///< the request in flight, for cancel()
    bool cancelled = false;
};

WebhookSink::WebhookSink(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
WebhookSink::~WebhookSink() = default;

Result<std::unique_ptr<WebhookSink>> WebhookSink::create(WebhookSettings settings) {
    auto url = parseUrl(settings.url);
    if (!url)
        return url.error();
#ifndef CPPHTTPLIB_OPENSSL_SUPPORT
    if (url->scheme == "https")
        return makeError(ErrorCode::Unsupported,
                         "webhook " + settings.url + ": https needs cpp-httplib with TLS");
#endif
    auto impl = std::make_unique<Impl>();
    impl->settings = std::move(settings);
    impl->url = *url;
    return std::unique_ptr<WebhookSink>(new WebhookSink(std::move(impl)));
}

std::string WebhookSink::name() const {
    return "webhook " + impl_->url.redacted();
}

std::string WebhookSink::body(const AlertRecord& alert) const {
    if (impl_->settings.format == WebhookSettings::Format::Slack) {
        std::string text = std::string("[") + toString(alert.severity) + "] " +
                           toString(alert.kind) + ": " + alert.message;
        if (alert.runId && alert.sectionId)
            text += " (run " + std::to_string(*alert.runId) + ", section " +
                    std::to_string(*alert.sectionId) + ")";
        else if (alert.runId)
            text += " (run " + std::to_string(*alert.runId) + ")";
        else if (alert.sectionId)
            text += " (section " + std::to_string(*alert.sectionId) + ")";
        return nlohmann::json{{"text", text}}.dump();
    }
    nlohmann::json j = toJson(alert);
    j["station"] = impl_->station;
    return j.dump();
}

Result<void> WebhookSink::deliver(const AlertRecord& alert) {
    const std::string what = name();
    {
        std::lock_guard lock(impl_->mutex);
        if (impl_->cancelled)
            return makeError(ErrorCode::Cancelled, what + ": stopped");
    }
    httplib::Client client(impl_->url.base());
    const auto timeout = impl_->settings.timeout;
    client.set_connection_timeout(timeout);
    client.set_read_timeout(timeout);
    client.set_write_timeout(timeout);
    client.set_follow_location(false);
    client.set_default_headers({{"User-Agent", "slicestationd"}});
    {
        std::lock_guard lock(impl_->mutex);
        impl_->current = &client;
    }
    const std::string payload = body(alert);
    auto res = client.Post(impl_->url.path, payload, "application/json");
    bool cancelled = false;
    {
        std::lock_guard lock(impl_->mutex);
        impl_->current = nullptr;
        cancelled = impl_->cancelled;
    }
    if (cancelled)
        return makeError(ErrorCode::Cancelled, what + ": stopped");
    if (!res) {
        const auto err = res.error();
        const auto code = err == httplib::Error::Read || err == httplib::Error::ConnectionTimeout
                              ? ErrorCode::Timeout
                              : ErrorCode::Disconnected;
        return makeError(code, what + ": no response: " + describe(err));
    }
    if (res->status < 200 || res->status > 299) {
        std::string snippet = res->body.substr(0, 200);
        return makeError(ErrorCode::IoError, what + ": HTTP status " + std::to_string(res->status) +
                                                 (snippet.empty() ? "" : ": " + snippet));
    }
    return {};
}

void WebhookSink::cancel() noexcept {
    std::lock_guard lock(impl_->mutex);
    impl_->cancelled = true;
    if (impl_->current)
        impl_->current->stop();
}

} // namespace slicestation::daemon
