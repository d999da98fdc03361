// slicectl stage: commissioning commands for the technician (JSON on stdout).
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/config/station_config.hpp"
#include "slicestation/daemon/devices/devices.hpp"

#include <nlohmann/json.hpp>

#include <iostream>
#include <optional>

namespace slicestation::daemon {

namespace {
nlohmann::json toJson(const hw::StagePosition& p, bool hasZ) {
    nlohmann::json j{{"x_um", p.xUm}, {"y_um", p.yUm}};
    if (hasZ)
        j["z_um"] = p.zUm;
    return j;
}
/// The configured stage, saying so on stderr when it is simulated.
core::Result<std::unique_ptr<hw::Stage>> openAnnounced(const StageConfig& sc,
                                                       const std::string& file, bool& simulated) {
    auto opened = openStage(sc, simulated);
    if (opened && simulated)
        std::cerr << "slicectl stage: SIMULATED stage (stage.driver = \"sim\" in " << file << ")\n";
    return opened;
}

} // namespace

CommandRunner addStageCommand(CLI::App& app) {
    struct Opts {
        std::string config;
        std::optional<double> x, y, z;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("stage", "Commission the motorised stage (prints JSON)");
    cmd->add_option("--config", o->config, "Station file (TOML)")->required();
    cmd->require_subcommand(1);
    auto* position = cmd->add_subcommand("position", "Read the feedback position");
    auto* move = cmd->add_subcommand("move", "Move to an absolute position and wait until settled");
    move->add_option("--x-um", o->x, "Target X, micrometres")->required();
    move->add_option("--y-um", o->y, "Target Y, micrometres")->required();
    move->add_option("--z-um", o->z, "Target Z, micrometres (default: stay)");
    auto* home = cmd->add_subcommand("home", "Run the drives' homing");
    auto* stop = cmd->add_subcommand("stop", "Stop every axis now");
    auto* reset = cmd->add_subcommand("reset-alarm", "Read, then reset, the drives' alarms");

    return [=]() -> int {
        if (!*cmd)
            return -1;
        const char* name = "stage";
        auto cfg = loadStationConfig(o->config);
        if (!cfg)
            return reportError(name, cfg.error());
        const auto& sc = cfg->stage;
        bool simulated = false;
        auto opened = openAnnounced(sc, o->config, simulated);
        if (!opened)
            return reportError(name, opened.error());
        hw::Stage& stage = **opened;
        const auto limits = stage.limits();
        const bool hasZ = limits.z.has_value();
        const std::chrono::milliseconds ioTimeout{2000};
        nlohmann::json out;
        if (*position) {
            auto p = stage.position(ioTimeout);
            if (!p)
                return reportError(name, p.error());
            out = {{"position", toJson(*p, hasZ)}};
        } else if (*move) {
            if (o->z && !hasZ)
                return reportError(name,
                                   core::makeError(core::ErrorCode::InvalidArgument,
                                                   "--z-um given but the stage has no z axis"));
            hw::StagePosition target{*o->x, *o->y, 0};
            // Soft limits are checked before anything is sent, even the position read for Z.
            hw::StageLimits xy = limits;
            if (!o->z)
                xy.z.reset();
            else
                target.zUm = *o->z;
            if (auto r = hw::checkWithinLimits(xy, target); !r)
                return reportError(name, r.error());
            if (hasZ && !o->z) {
                auto p = stage.position(ioTimeout);
                if (!p)
                    return reportError(name, p.error());
                target.zUm = p->zUm;
            }
            auto r = stage.moveTo(target, sc.moveTimeout);
            if (!r)
                return reportError(name, r.error());
            out = {{"position", toJson(*r, hasZ)}, {"target", toJson(target, hasZ)}};
        } else if (*home) {
            auto r = stage.home(sc.homeTimeout);
            if (!r)
                return reportError(name, r.error());
            out = {{"position", toJson(*r, hasZ)}, {"homed", true}};
        } else if (*stop) {
            stage.stop();
            out = {{"stopped", true}};
        } else if (*reset) {
            auto before = stage.alarm(ioTimeout);
            if (!before)
                return reportError(name, before.error());
            auto r = stage.resetAlarm(ioTimeout);
            if (!r)
                return reportError(name, r.error());
            auto after = stage.alarm(ioTimeout);
            if (!after)
                return reportError(name, after.error());
            out = {{"alarm_before",
                    {{"active", before->active}, {"code", before->code}, {"axis", before->axis}}},
                   {"alarm_after",
                    {{"active", after->active}, {"code", after->code}, {"axis", after->axis}}}};
            if (after->active) {
                std::cout << out.dump(2) << "\n";
                return reportError(name,
                                   core::makeError(core::ErrorCode::Alarm,
                                                   "the alarm is still active after the reset"));
            }
        }
        out["simulated"] = simulated;
        std::cout << out.dump(2) << "\n";
        return 0;
    };
}

} // namespace slicestation::daemon
