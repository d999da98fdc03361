#pragma once
// Private to alerts/: helpers the settings and the channels share.
#include "slicestation/core/result.hpp"

#include <httplib.h>

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

struct ParsedUrl {
    std::string scheme; ///< http or https
    std::string host;   ///< as written, [brackets] kept for IPv6
    int port = 0;
    std::string path; ///< at least "/", query included
    /// scheme://host:port, what httplib::Client takes.
    std::string base() const { return scheme + "://" + host + ":" + std::to_string(port); }
    /// For logs and stats: the path of a webhook URL often is its secret (Slack, Mattermost).
    std::string redacted() const {
        return scheme + "://" + host + ":" + std::to_string(port) + (path == "/" ? "/" : "/...");
    }
};

/// Parses a webhook URL (http or https, host, optional port, path). InvalidArgument naming what
/// is wrong.
core::Result<ParsedUrl> parseUrl(const std::string& url);
/// A cpp-httplib error in words.
std::string describe(httplib::Error e);
/// This machine's name, for the payloads ("unknown" when it has none).
std::string hostName();
/// argv joined for messages, cut to 120 characters.
std::string commandLine(const std::vector<std::string>& argv);
/// The id, or "" when none.
std::string optionalId(const std::optional<std::int64_t>& id);

} // namespace slicestation::daemon
