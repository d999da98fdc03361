#include "http_util.hpp"

#include "slicestation/core/codec.hpp"
#include "slicestation/pipeline/display.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <vector>

namespace slicestation::daemon::http {

using core::ErrorCode;

int httpStatus(const core::Error& e, RequestKind kind) noexcept {
    switch (e.code) {
    case ErrorCode::InvalidArgument:
        return kind == RequestKind::Control ? 409 : 400;
    case ErrorCode::OutOfRange:
    case ErrorCode::Unsupported:
    case ErrorCode::NoTissue:
        return 400;
    case ErrorCode::NotFound:
        return 404;
    default:
        return 500;
    }
}

std::string dumpJson(const nlohmann::json& j) {
    return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

void sendJson(httplib::Response& res, const nlohmann::json& j, int status) {
    res.status = status;
    res.set_content(dumpJson(j), "application/json");
}

void sendError(httplib::Response& res, int status, const std::string& message) {
    sendJson(res, {{"error", message}}, status);
}

void sendError(httplib::Response& res, const core::Error& e, RequestKind kind) {
    sendError(res, httpStatus(e, kind), e.message);
}

std::string echo(const std::string& s) {
    return "\"" + (s.size() > 40 ? s.substr(0, 40) + "..." : s) + "\"";
}

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

std::optional<int> intQuery(const httplib::Request& req, httplib::Response& res, const char* name,
                            int lo, int hi, std::optional<int> fallback) {
    if (!req.has_param(name)) {
        if (!fallback)
            sendError(res, 400, std::string("missing query parameter ") + name);
        return fallback;
    }
    const std::string s = req.get_param_value(name);
    int v = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc() || p != s.data() + s.size() || v < lo || v > hi) {
        sendError(res, 400,
                  std::string(name) + ": expected an integer " + std::to_string(lo) + ".." +
                      std::to_string(hi) + ", got " + echo(s));
        return std::nullopt;
    }
    return v;
}

void sendImage(httplib::Response& res, const cv::Mat& image, int width, const std::string& ext) {
    cv::Mat m = pipeline::displayStretch(image);
    if (m.empty())
        return sendError(res, 500, "image cannot be shown");
    if (width < m.cols) {
        cv::Mat small;
        const int height =
            std::max(1, static_cast<int>(std::lround(m.rows * double(width) / m.cols)));
        cv::resize(m, small, cv::Size(width, height), 0, 0, cv::INTER_AREA);
        m = small;
    }
    auto buf = ext == ".jpg" ? core::encodeJpeg(m, 85) : core::encodePng(m);
    if (!buf)
        return sendError(res, 500, "cannot encode the image: " + buf.error().message);
    res.set_header("Cache-Control", "no-store");
    res.set_content(std::string(buf->begin(), buf->end()),
                    ext == ".jpg" ? "image/jpeg" : "image/png");
}

Authoriser bearerAuthoriser(std::string token) {
    return [token = std::move(token)](const httplib::Request& req, httplib::Response& res) {
        if (token.empty()) {
            sendError(res, 401, "control is disabled: no daemon.token configured");
            return false;
        }
        const std::string expected = "Bearer " + token;
        const std::string got = req.get_header_value("Authorization");
        // Constant-time comparison: the token is a secret.
        const bool same = got.size() == expected.size();
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
}

} // namespace slicestation::daemon::http
