#pragma once
// Private to http/: answering a request. Every error reaches the client through sendError,
// with its status from the one table httpStatus() (docs/architecture.md, "HTTP errors").
#include "slicestation/core/result.hpp"

#include <httplib.h>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include <cstdint>
#include <functional>
#include <optional>
#include <string>

namespace slicestation::daemon::http {

/// What a request asked for, which decides what an InvalidArgument from the station means.
enum class RequestKind {
    Read,   ///< a GET, or a plan submitted: InvalidArgument is the request's fault (400)
    Control ///< pause, resume, cancel, rescan, acknowledge: InvalidArgument is "not now" (409)
};

/// The one mapping from a station error to an HTTP status:
/// | code                               | Read | Control |
/// |------------------------------------|------|---------|
/// | InvalidArgument                    | 400  | 409     |
/// | OutOfRange, Unsupported, NoTissue  | 400  | 400     |
/// | NotFound                           | 404  | 404     |
/// | anything else (a station fault)    | 500  | 500     |
int httpStatus(const core::Error& e, RequestKind kind) noexcept;

/// Never throws on what it sends: bytes that are not UTF-8 become U+FFFD.
std::string dumpJson(const nlohmann::json& j);
void sendJson(httplib::Response& res, const nlohmann::json& j, int status = 200);
/// {"error": message} with `status`.
void sendError(httplib::Response& res, int status, const std::string& message);
/// {"error": e.message} with httpStatus(e, kind).
void sendError(httplib::Response& res, const core::Error& e, RequestKind kind = RequestKind::Read);

/// Something from the request, for a message: quoted and cut to 40 bytes.
std::string echo(const std::string& s);

/// The numeric id in path capture 1; nullopt (400 sent) for anything else.
std::optional<std::int64_t> idParam(const httplib::Request& req, httplib::Response& res);
/// An integer query parameter within [lo, hi]; `fallback` when absent; nullopt (400 sent) when
/// bad, or absent without a fallback.
std::optional<int> intQuery(const httplib::Request& req, httplib::Response& res, const char* name,
                            int lo, int hi, std::optional<int> fallback);

/// Made 8-bit for display (pipeline::displayStretch), scaled to `width` (never up) and encoded;
/// `ext` ".jpg" or ".png". 500 when it cannot be shown.
void sendImage(httplib::Response& res, const cv::Mat& image, int width, const std::string& ext);

/// Control requests need `Authorization: Bearer <token>`; false (401 sent) otherwise.
using Authoriser = std::function<bool(const httplib::Request&, httplib::Response&)>;
Authoriser bearerAuthoriser(std::string token);

} // namespace slicestation::daemon::http
