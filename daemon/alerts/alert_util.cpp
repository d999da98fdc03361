#include "alert_util.hpp"

#include <unistd.h>

#include <exception>
#include <string>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

Result<ParsedUrl> parseUrl(const std::string& url) {
    const auto bad = [&](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "\"" + url + "\": " + what);
    };
    ParsedUrl u;
    std::string rest;
    if (url.starts_with("http://")) {
        u.scheme = "http";
        u.port = 80;
        rest = url.substr(7);
    } else if (url.starts_with("https://")) {
        u.scheme = "https";
        u.port = 443;
        rest = url.substr(8);
    } else {
        return bad("expected http://host[:port][/path] or https://...");
    }
    if (std::any_of(url.begin(), url.end(), [](char c) { return c <= ' ' || c == 0x7f; }))
        return bad("contains white space or control characters");
    const auto slash = rest.find_first_of("/?#");
    std::string authority = rest.substr(0, slash);
    u.path = slash == std::string::npos ? "/" : rest.substr(slash);
    if (!u.path.starts_with("/"))
        u.path = "/" + u.path;
    if (const auto hash = u.path.find('#'); hash != std::string::npos)
        u.path.resize(hash);
    if (authority.find('@') != std::string::npos)
        return bad("user:password@ in the URL is not supported");
    std::string portText;
    if (authority.starts_with("[")) {
        const auto close = authority.find(']');
        if (close == std::string::npos)
            return bad("unterminated [IPv6 address]");
        u.host = authority.substr(0, close + 1);
        const std::string after = authority.substr(close + 1);
        if (!after.empty()) {
            if (!after.starts_with(":"))
                return bad("expected :port after the IPv6 address");
            portText = after.substr(1);
        }
        if (u.host.size() < 3 ||
            u.host.find_first_not_of("0123456789abcdefABCDEF:.", 1) != u.host.size() - 1)
            return bad("bad IPv6 address " + u.host);
    } else {
        const auto colon = authority.find(':');
        u.host = authority.substr(0, colon);
        if (colon != std::string::npos)
            portText = authority.substr(colon + 1);
        if (u.host.empty())
            return bad("no host");
        if (!std::all_of(u.host.begin(), u.host.end(), [](char c) {
                return std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '-' ||
                       c == '_';
            }))
            return bad("bad host name \"" + u.host + "\"");
    }
    if (!portText.empty() || authority.ends_with(":")) {
        if (portText.empty() || portText.size() > 5 ||
            !std::all_of(portText.begin(), portText.end(),
                         [](char c) { return c >= '0' && c <= '9'; }))
            return bad("bad port \"" + portText + "\"");
        u.port = std::stoi(portText);
        if (u.port < 1 || u.port > 65535)
            return bad("port " + portText + " is outside 1..65535");
    }
    return u;
}

std::string describe(httplib::Error e) {
    switch (e) {
    case httplib::Error::Connection:
        return "cannot connect";
    case httplib::Error::ConnectionTimeout:
        return "connect timed out";
    case httplib::Error::Read:
        return "no answer in time, or the connection was closed";
    case httplib::Error::Write:
        return "sending the request failed";
    case httplib::Error::SSLConnection:
        return "TLS handshake failed";
    case httplib::Error::SSLLoadingCerts:
        return "cannot load the system's CA certificates";
    case httplib::Error::SSLServerVerification:
        return "the server's certificate was not accepted";
    default:
        return httplib::to_string(e);
    }
}

std::string hostName() {
    char buf[256] = {};
    if (gethostname(buf, sizeof buf - 1) != 0)
        return "unknown";
    return buf;
}

std::string commandLine(const std::vector<std::string>& argv) {
    std::string s;
    for (const auto& a : argv) {
        if (!s.empty())
            s += ' ';
        s += a;
    }
    if (s.size() > 120)
        s = s.substr(0, 117) + "...";
    return s;
}

std::string optionalId(const std::optional<std::int64_t>& id) {
    return id ? std::to_string(*id) : std::string();
}

} // namespace slicestation::daemon
