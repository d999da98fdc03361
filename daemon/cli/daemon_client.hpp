#pragma once
// Private to cli/: the HTTP client of the slicectl commands that talk to a running slicestationd
// (cli_daemon.cpp defines it; damage_command.cpp uses it too).
#include "slicestation/core/result.hpp"

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <functional>
#include <string>

namespace slicestation::daemon::client {

struct Connection {
    std::string url;    ///< http://host:port
    std::string token;  ///< bearer token for control commands
    std::string config; ///< station file to read port and token from
};

/// --url, --token, --config on `cmd`.
void addConnectionOptions(CLI::App* cmd, Connection& c);

struct Reply {
    int status = 0;
    std::string body;
};

/// One request (GET, else POST with `body`); Disconnected when the daemon cannot be reached.
core::Result<Reply> request(Connection c, const std::string& method, const std::string& path,
                            const std::string& body = {},
                            const std::string& contentType = "application/json");

/// The exit code of a daemon reply: 2xx ok; 400, 404, 413 the input; 409 a conflict with the
/// run's state; 401, 403 and 5xx the daemon refused.
int exitCodeOf(int status);

using Printer = std::function<void(const nlohmann::json&)>;

/// On success prints the reply: `print` for people, or the JSON (pretty) with --json or without
/// a printer; `raw` prints the body as it came. On failure the daemon's message. Exit code.
int finish(const char* name, const core::Result<Reply>& r, bool json, const Printer& print = {},
           bool raw = false);

/// A field for a table: strings as they are, numbers plain, booleans yes/no, null "".
std::string text(const nlohmann::json& j, const char* key);

} // namespace slicestation::daemon::client
