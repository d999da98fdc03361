// slicectl commands that talk to a running slicestationd over its HTTP API: scan submit, status,
// runs, sections, section, pause, resume, cancel, rescan, alerts, export.
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"

#include <httplib.h>
#include <nlohmann/json.hpp>

#include <cstdlib>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

struct Connection {
    std::string url;    ///< http://host:port
    std::string token;  ///< bearer token for control commands
    std::string config; ///< station file to read port and token from
};

void addConnectionOptions(CLI::App* cmd, Connection& c) {
    cmd->add_option("--url", c.url,
                    "Daemon address (default http://127.0.0.1:8470, or from --config)");
    cmd->add_option("--token", c.token,
                    "Bearer token for control (default $SLICESTATION_TOKEN, or from --config)");
    cmd->add_option("--config", c.config,
                    "Station file: read daemon.http_port and daemon.token from it");
}

struct Reply {
    int status = 0;
    std::string body;
};

core::Result<Reply> request(Connection c, const std::string& method, const std::string& path,
                            const std::string& body = {},
                            const std::string& contentType = "application/json") {
    std::string url = c.url;
    if (!c.config.empty()) {
        auto doc = readDocument(c.config);
        if (!doc)
            return doc.error();
        auto s = parseDaemonSettings(*doc, c.config);
        if (!s)
            return s.error();
        if (url.empty()) {
            const std::string host = s->httpBind == "0.0.0.0" ? "127.0.0.1" : s->httpBind;
            url = "http://" + host + ":" + std::to_string(s->httpPort);
        }
        if (c.token.empty())
            c.token = s->token;
    }
    if (url.empty())
        url = "http://127.0.0.1:8470";
    if (c.token.empty())
        if (const char* t = std::getenv("SLICESTATION_TOKEN"))
            c.token = t;
    httplib::Client cli(url);
    if (!cli.is_valid())
        return makeError(ErrorCode::InvalidArgument, "--url: cannot use \"" + url + "\"");
    cli.set_connection_timeout(3, 0);
    cli.set_read_timeout(30, 0);
    httplib::Headers headers;
    if (!c.token.empty())
        headers.emplace("Authorization", "Bearer " + c.token);
    httplib::Result res =
        method == "GET" ? cli.Get(path, headers) : cli.Post(path, headers, body, contentType);
    if (!res)
        return makeError(ErrorCode::Disconnected, "cannot reach slicestationd at " + url + " (" +
                                                      httplib::to_string(res.error()) +
                                                      "); is it running?");
    return Reply{res->status, res->body};
}

/// Prints the body (JSON pretty) on success; the daemon's message on failure. Exit code.
int finish(const char* name, const core::Result<Reply>& r, bool raw = false) {
    if (!r)
        return reportError(name, r.error());
    if (r->status >= 200 && r->status < 300) {
        if (raw) {
            std::cout << r->body;
        } else {
            auto j = nlohmann::json::parse(r->body, nullptr, false);
            std::cout << (j.is_discarded() ? r->body : j.dump(2)) << "\n";
        }
        return 0;
    }
    auto j = nlohmann::json::parse(r->body, nullptr, false);
    const std::string msg =
        !j.is_discarded() && j.contains("error") ? j["error"].get<std::string>() : r->body;
    std::cerr << "slicectl " << name << ": error: " << msg << " (HTTP " << r->status << ")\n";
    return r->status == 400 || r->status == 404 || r->status == 409 ? 2 : 1;
}

/// The options of the daemon client commands.
struct DaemonOpts {
    Connection c;
    std::string plan;
    std::int64_t id = 0;
    bool all = false;
    std::string action = "accept";
    std::string format = "json";
    std::string output;
    bool resetAlarm = false;
};

} // namespace

CommandRunner addDaemonCommands(CLI::App& app) {
    auto o = std::make_shared<DaemonOpts>();
    auto* scan = app.add_subcommand("scan", "Submit scan plans to the daemon");
    auto* submit =
        scan->add_subcommand("submit", "Queue a scan plan (TOML or JSON); prints the run id");
    submit->add_option("PLAN", o->plan, "Plan file")->required()->check(CLI::ExistingFile);
    addConnectionOptions(submit, o->c);
    scan->require_subcommand(1);

    auto* status = app.add_subcommand("status", "The daemon's status (JSON)");
    auto* runs = app.add_subcommand("runs", "List runs");
    auto* sections = app.add_subcommand("sections", "List the sections of a run");
    sections->add_option("RUN", o->id, "Run id")->required();
    auto* section =
        app.add_subcommand("section", "One section in detail: captures, registrations, damage");
    section->add_option("SECTION", o->id, "Section id")->required();
    auto* pause = app.add_subcommand("pause", "Pause a run (between sections)");
    pause->add_option("RUN", o->id, "Run id")->required();
    auto* resume = app.add_subcommand("resume", "Resume a paused run");
    resume->add_option("RUN", o->id, "Run id")->required();
    resume->add_flag(
        "--reset-stage-alarm", o->resetAlarm,
        "The cause of a stage alarm is cleared: reset the drives' alarm before going on");
    auto* cancel =
        app.add_subcommand("cancel", "Cancel a run (preempts the move or capture in progress)");
    cancel->add_option("RUN", o->id, "Run id")->required();
    auto* rescan =
        app.add_subcommand("rescan", "Capture a re-mounted section again (keeps the old records)");
    rescan->add_option("SECTION", o->id, "Section id")->required();
    auto* alerts = app.add_subcommand("alerts", "List open alerts, or acknowledge one");
    alerts->add_flag("--all", o->all, "Also list acknowledged alerts");
    auto* ack = alerts->add_subcommand("ack", "Acknowledge an alert");
    ack->add_option("ALERT", o->id, "Alert id")->required();
    ack->add_option("--action", o->action,
                    "\"rescan\" (re-mounted: capture again) or \"accept\" (as is)");
    addConnectionOptions(ack, o->c);
    auto* exp = app.add_subcommand("export",
                                   "Export a run: per section image, stage position, atlas slice, "
                                   "registration quality, damage");
    exp->add_option("RUN", o->id, "Run id")->required();
    exp->add_option("--format", o->format, "csv or json")->check(CLI::IsMember({"csv", "json"}));
    exp->add_option("--output", o->output, "Write to this file instead of stdout");
    for (auto* c : {status, runs, sections, section, pause, resume, cancel, rescan, alerts, exp})
        addConnectionOptions(c, o->c);

    return [=]() -> int {
        const std::string id = std::to_string(o->id);
        if (*scan && *submit) {
            std::ifstream in(o->plan);
            std::stringstream ss;
            ss << in.rdbuf();
            const bool json = o->plan.ends_with(".json");
            return finish("scan submit", request(o->c, "POST", "/api/runs", ss.str(),
                                                 json ? "application/json" : "application/toml"));
        }
        if (*status)
            return finish("status", request(o->c, "GET", "/api/status"));
        if (*runs)
            return finish("runs", request(o->c, "GET", "/api/runs"));
        if (*sections)
            return finish("sections", request(o->c, "GET", "/api/runs/" + id + "/sections"));
        if (*section)
            return finish("section", request(o->c, "GET", "/api/sections/" + id));
        if (*pause)
            return finish("pause", request(o->c, "POST", "/api/runs/" + id + "/pause"));
        if (*resume)
            return finish("resume",
                          request(o->c, "POST", "/api/runs/" + id + "/resume",
                                  nlohmann::json{{"reset_stage_alarm", o->resetAlarm}}.dump()));
        if (*cancel)
            return finish("cancel", request(o->c, "POST", "/api/runs/" + id + "/cancel"));
        if (*rescan)
            return finish("rescan", request(o->c, "POST", "/api/sections/" + id + "/rescan"));
        if (*alerts && *ack)
            return finish("alerts ack", request(o->c, "POST", "/api/alerts/" + id + "/ack",
                                                nlohmann::json{{"action", o->action}}.dump()));
        if (*alerts)
            return finish("alerts",
                          request(o->c, "GET", o->all ? "/api/alerts" : "/api/alerts?open=1"));
        if (*exp) {
            auto r = request(o->c, "GET", "/api/runs/" + id + "/export?format=" + o->format);
            if (o->output.empty() || !r || r->status != 200)
                return finish("export", r, true);
            std::ofstream out(o->output, std::ios::binary);
            out << r->body;
            out.close();
            if (!out)
                return reportError("export",
                                   makeError(ErrorCode::IoError, "cannot write " + o->output));
            return 0;
        }
        return -1;
    };
}

} // namespace slicestation::daemon
