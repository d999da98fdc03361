// slicectl commands that talk to a running slicestationd over its HTTP API: scan submit, status,
// runs, sections, section, pause, resume, cancel, rescan, alerts, export.
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/cli/export_command.hpp"
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"

#include "daemon_client.hpp"

#include <httplib.h>
#include <nlohmann/json.hpp>

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <iostream>
#include <memory>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace client {

void addConnectionOptions(CLI::App* cmd, Connection& c) {
    cmd->add_option("--url", c.url,
                    "Daemon address (default http://127.0.0.1:8470, or from --config)");
    cmd->add_option("--token", c.token,
                    "Bearer token for control (default $SLICESTATION_TOKEN, or from --config)");
    cmd->add_option("--config", c.config,
                    "Station file: read daemon.http_port and daemon.token from it");
}

core::Result<Reply> request(Connection c, const std::string& method, const std::string& path,
                            const std::string& body, const std::string& contentType) {
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

int exitCodeOf(int status) {
    if (status >= 200 && status < 300)
        return kExitOk;
    if (status == 409)
        return kExitConflict;
    if (status == 400 || status == 404 || status == 413 || status == 422)
        return kExitInput;
    return kExitUnreachable;
}

int finish(const char* name, const core::Result<Reply>& r, bool json, const Printer& print,
           bool raw) {
    if (!r)
        return reportError(name, r.error());
    if (r->status >= 200 && r->status < 300) {
        if (raw) {
            std::cout << r->body;
            return kExitOk;
        }
        auto j = nlohmann::json::parse(r->body, nullptr, false);
        if (j.is_discarded())
            std::cout << r->body << "\n";
        else if (json || !print)
            std::cout << j.dump(2) << "\n";
        else
            print(j);
        return kExitOk;
    }
    auto j = nlohmann::json::parse(r->body, nullptr, false);
    const std::string msg = !j.is_discarded() && j.contains("error") && j["error"].is_string()
                                ? j["error"].get<std::string>()
                                : r->body;
    std::cerr << "slicectl " << name << ": error: " << msg << " (HTTP " << r->status << ")\n";
    return exitCodeOf(r->status);
}

std::string text(const nlohmann::json& j, const char* key) {
    if (!j.contains(key) || j[key].is_null())
        return "";
    const auto& v = j[key];
    if (v.is_string())
        return v.get<std::string>();
    if (v.is_number_float())
        return plainNumber(v.get<double>());
    if (v.is_boolean())
        return v.get<bool>() ? "yes" : "no";
    return v.dump();
}

} // namespace client

namespace {

using namespace client;

void printStatus(const nlohmann::json& j) {
    std::vector<std::vector<std::string>> rows{{"state", text(j, "state")},
                                               {"step", text(j, "activity")}};
    if (j.contains("run") && j["run"].is_object()) {
        const auto& r = j["run"];
        rows.push_back({"run", "#" + text(r, "id") + " " + text(r, "name") + ", " +
                                   text(r, "state") + ", " + text(r, "done") + "/" +
                                   text(r, "sections") + " sections"});
    } else {
        rows.push_back({"run", "none active"});
    }
    rows.push_back({"open alerts", text(j, "open_alerts")});
    if (j.contains("free_mb") && j["free_mb"].is_number())
        rows.push_back({"free space", plainNumber(std::round(j["free_mb"].get<double>())) + " MB"});
    if (j.contains("simulated") && j["simulated"].is_object()) {
        std::string sim;
        if (j["simulated"].value("stage", false))
            sim += "stage ";
        if (j["simulated"].value("camera", false))
            sim += "camera";
        rows.push_back({"simulated", sim.empty() ? "nothing" : sim});
    }
    if (j.contains("atlas") && j["atlas"].is_object())
        rows.push_back(
            {"atlas", text(j["atlas"], "slices") + " slices in " + text(j["atlas"], "dir")});
    rows.push_back({"state dir", text(j, "state_dir")});
    std::cout << formatTable({"STATUS", ""}, rows);
}

void printRuns(const nlohmann::json& j) {
    std::vector<std::vector<std::string>> rows;
    for (const auto& r : j)
        rows.push_back(
            {text(r, "id"), text(r, "name"),
             text(r, "state") + (text(r, "reason").empty() ? "" : " (" + text(r, "reason") + ")"),
             text(r, "done") + "/" + text(r, "sections"), localTime(text(r, "created_utc")),
             localTime(text(r, "started_utc")), localTime(text(r, "ended_utc"))});
    std::cout << formatTable({"ID", "NAME", "STATE", "DONE", "CREATED", "STARTED", "ENDED"}, rows)
              << "(" << localZoneLabel() << ")\n";
}

void printSections(const nlohmann::json& j) {
    std::vector<std::vector<std::string>> rows;
    for (const auto& s : j)
        rows.push_back({text(s, "id"), text(s, "slide"), text(s, "name"), text(s, "state"),
                        text(s, "attempts"), text(s, "expected_slice"), text(s, "reason")});
    std::cout << formatTable(
        {"ID", "SLIDE", "SECTION", "STATE", "ATTEMPTS", "PLANNED SLICE", "REASON"}, rows);
}

void printAlerts(const nlohmann::json& j) {
    std::vector<std::vector<std::string>> rows;
    for (const auto& a : j)
        rows.push_back({text(a, "id"), localTime(text(a, "raised_utc")), text(a, "severity"),
                        text(a, "kind"), text(a, "section_id"),
                        a.value("open", false) ? "open" : "answered: " + text(a, "ack_action"),
                        text(a, "message")});
    if (rows.empty()) {
        std::cout << "no alerts\n";
        return;
    }
    std::cout << formatTable({"ID", "RAISED", "SEVERITY", "KIND", "SECTION", "STATE", "MESSAGE"},
                             rows)
              << "(" << localZoneLabel() << ")\n";
}

/// A control's answer for people: one line.
Printer saying(std::string what) {
    return [what = std::move(what)](const nlohmann::json&) { std::cout << what << "\n"; };
}

/// The options of the daemon client commands.
struct DaemonOpts {
    Connection c;
    std::string plan;
    std::int64_t id = 0;
    bool all = false;
    std::string action = "accept";
    bool json = false;
    std::string format = "json";
    std::string output;
    std::string result; ///< export --result: one registration, no daemon
    bool resetAlarm = false;
};

/// The subcommands of addDaemonCommands, to tell which one was given.
struct DaemonCommands {
    CLI::App *scan = nullptr, *submit = nullptr, *status = nullptr, *runs = nullptr,
             *sections = nullptr, *section = nullptr, *pause = nullptr, *resume = nullptr,
             *cancel = nullptr, *rescan = nullptr, *alerts = nullptr, *ack = nullptr,
             *exp = nullptr;
};

DaemonCommands declareDaemonCommands(CLI::App& app, const std::shared_ptr<DaemonOpts>& o) {
    DaemonCommands c;
    c.scan = app.add_subcommand("scan", "Submit scan plans to the daemon");
    c.submit =
        c.scan->add_subcommand("submit", "Queue a scan plan (TOML or JSON); prints the run id");
    c.submit->add_option("PLAN", o->plan, "Plan file")->required()->check(CLI::ExistingFile);
    addConnectionOptions(c.submit, o->c);
    c.scan->require_subcommand(1);

    c.status = app.add_subcommand("status", "The daemon's status");
    c.runs = app.add_subcommand("runs", "List runs");
    c.sections = app.add_subcommand("sections", "List the sections of a run");
    c.sections->add_option("RUN", o->id, "Run id")->required();
    c.section =
        app.add_subcommand("section", "One section in detail: captures, registrations, damage");
    c.section->add_option("SECTION", o->id, "Section id")->required();
    c.pause = app.add_subcommand("pause", "Pause a run (between sections)");
    c.pause->add_option("RUN", o->id, "Run id")->required();
    c.resume = app.add_subcommand("resume", "Resume a paused run");
    c.resume->add_option("RUN", o->id, "Run id")->required();
    c.resume->add_flag(
        "--reset-stage-alarm", o->resetAlarm,
        "The cause of a stage alarm is cleared: reset the drives' alarm before going on");
    c.cancel =
        app.add_subcommand("cancel", "Cancel a run (preempts the move or capture in progress)");
    c.cancel->add_option("RUN", o->id, "Run id")->required();
    c.rescan =
        app.add_subcommand("rescan", "Capture a re-mounted section again (keeps the old records)");
    c.rescan->add_option("SECTION", o->id, "Section id")->required();
    c.alerts = app.add_subcommand("alerts", "List open alerts, or acknowledge one");
    c.alerts->add_flag("--all", o->all, "Also list acknowledged alerts");
    c.ack = c.alerts->add_subcommand("ack", "Acknowledge an alert");
    c.ack->add_option("ALERT", o->id, "Alert id")->required();
    c.ack
        ->add_option("--action", o->action,
                     "rescan (re-mounted: capture again) or accept (as is; the default)")
        ->check(CLI::IsMember({"rescan", "accept"}));
    addConnectionOptions(c.ack, o->c);
    c.exp = app.add_subcommand(
        "export", "Export a run (or one result): csv/json summary, QuickNII/VisuAlign JSON, "
                  "QuPath GeoJSON (docs/results.md)");
    auto* run = c.exp->add_option("RUN", o->id, "Run id");
    auto* result = c.exp->add_option("--result", o->result,
                                     "Export this result.json (slicectl register's) instead "
                                     "of a run; no daemon needed");
    run->excludes(result);
    c.exp->add_option("--format", o->format, "csv, json, quicknii or qupath")
        ->check(CLI::IsMember({"csv", "json", "quicknii", "qupath"}));
    c.exp->add_option("--output", o->output,
                      "Write to this file instead of stdout (qupath for a run: a directory)");
    for (auto* sub : {c.status, c.runs, c.sections, c.section, c.pause, c.resume, c.cancel,
                      c.rescan, c.alerts, c.exp})
        addConnectionOptions(sub, o->c);
    for (auto* sub : {c.submit, c.status, c.runs, c.sections, c.pause, c.resume, c.cancel, c.rescan,
                      c.alerts, c.ack})
        sub->add_flag("--json", o->json,
                      "Print the daemon's JSON (for scripts) instead of a table");

    return c;
}

int runDaemonCommand(const DaemonOpts& o, const DaemonCommands& c) {
    const std::string id = std::to_string(o.id);
    const bool json = o.json;
    if (*c.scan && *c.submit) {
        std::ifstream in(o.plan);
        std::stringstream ss;
        ss << in.rdbuf();
        const bool isJson = o.plan.ends_with(".json");
        return finish("scan submit",
                      request(o.c, "POST", "/api/runs", ss.str(),
                              isJson ? "application/json" : "application/toml"),
                      json, [](const nlohmann::json& j) {
                          std::cout << "run " << text(j, "run_id") << " queued\n";
                      });
    }
    if (*c.status)
        return finish("status", request(o.c, "GET", "/api/status"), json, printStatus);
    if (*c.runs)
        return finish("runs", request(o.c, "GET", "/api/runs"), json, printRuns);
    if (*c.sections)
        return finish("sections", request(o.c, "GET", "/api/runs/" + id + "/sections"), json,
                      printSections);
    if (*c.section) // the detail is nested: JSON is its readable form
        return finish("section", request(o.c, "GET", "/api/sections/" + id), true);
    if (*c.pause)
        return finish("pause", request(o.c, "POST", "/api/runs/" + id + "/pause"), json,
                      saying("run " + id + ": pause requested (it stops between sections)"));
    if (*c.resume)
        return finish(
            "resume",
            request(o.c, "POST", "/api/runs/" + id + "/resume",
                    nlohmann::json{{"reset_stage_alarm", o.resetAlarm}}.dump()),
            json, saying("run " + id + " resumed" + (o.resetAlarm ? " (stage alarm reset)" : "")));
    if (*c.cancel)
        return finish("cancel", request(o.c, "POST", "/api/runs/" + id + "/cancel"), json,
                      saying("run " + id + " cancelled"));
    if (*c.rescan)
        return finish("rescan", request(o.c, "POST", "/api/sections/" + id + "/rescan"), json,
                      saying("section " + id + ": rescan requested"));
    if (*c.alerts && *c.ack)
        return finish("alerts ack",
                      request(o.c, "POST", "/api/alerts/" + id + "/ack",
                              nlohmann::json{{"action", o.action}}.dump()),
                      json, saying("alert " + id + " acknowledged (" + o.action + ")"));
    if (*c.alerts)
        return finish("alerts", request(o.c, "GET", o.all ? "/api/alerts" : "/api/alerts?open=1"),
                      json, printAlerts);
    if (*c.exp) {
        if (!o.result.empty())
            return exportResultFile(o.format, o.result, o.output);
        if (c.exp->count("RUN") == 0) {
            std::cerr << "slicectl export: error: give a RUN id or --result RESULT.json\n";
            return kExitUsage;
        }
        std::unique_ptr<Progress> waiting;
        if (o.format == "quicknii" || o.format == "qupath") {
            waiting = std::make_unique<Progress>("export");
            waiting->phase("the daemon is building the " + o.format + " export");
        }
        auto r = request(o.c, "GET", "/api/runs/" + id + "/export?format=" + o.format);
        waiting.reset();
        if (!r || r->status != 200)
            return finish("export", r, false, {}, true);
        return writeRunExport(o.format, r->body, o.output);
    }
    return -1;
}

} // namespace

CommandRunner addDaemonCommands(CLI::App& app) {
    auto o = std::make_shared<DaemonOpts>();
    const DaemonCommands c = declareDaemonCommands(app, o);
    CommandRunner damage = addDamageCommands(app); // damage_command.cpp
    return [o, c, damage]() -> int {
        const int r = runDaemonCommand(*o, c);
        return r != -1 ? r : damage();
    };
}

} // namespace slicestation::daemon
