// slicectl camera: commissioning command for the technician (JSON on stdout).
#include "slicestation/daemon/cli/cli_camera.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/config/station_config.hpp"
#include "slicestation/daemon/devices/devices.hpp"

#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

#include <iostream>
#include <optional>

namespace slicestation::daemon {

namespace {
nlohmann::json toJson(const hw::CameraSettings& s) {
    return {{"format", hw::toString(s.format)}, {"width", s.width},       {"height", s.height},
            {"exposure_us", s.exposureUs},      {"gain", s.analogueGain}, {"red_gain", s.redGain},
            {"blue_gain", s.blueGain}};
}

core::Result<cv::Mat> toMat(const hw::Frame& f) {
    const int type = f.format() == hw::PixelFormat::Mono16  ? CV_16UC1
                     : f.format() == hw::PixelFormat::Mono8 ? CV_8UC1
                                                            : CV_8UC3;
    cv::Mat m(f.height(), f.width(), type, const_cast<std::uint8_t*>(f.bytes().data()), f.stride());
    try {
        cv::Mat out;
        if (type == CV_8UC3)
            cv::cvtColor(m, out, cv::COLOR_RGB2BGR); // image files take BGR
        else
            out = m.clone();
        return out;
    } catch (const cv::Exception& e) {
        return core::makeError(core::ErrorCode::Internal, std::string("OpenCV: ") + e.what());
    }
}
/// A frame's format, size and metadata, as `slicectl camera capture` prints them.
nlohmann::json frameJson(const hw::Frame& frame) {
    const auto& m = frame.metadata;
    nlohmann::json meta{{"format", hw::toString(frame.format())},
                        {"width", frame.width()},
                        {"height", frame.height()},
                        {"exposure_us", m.exposureUs},
                        {"gain", m.analogueGain},
                        {"red_gain", m.redGain},
                        {"blue_gain", m.blueGain},
                        {"timestamp_ns", m.timestampNs},
                        {"sequence", m.sequence}};
    if (m.stage)
        meta["stage"] = {{"x_um", m.stage->xUm}, {"y_um", m.stage->yUm}, {"z_um", m.stage->zUm}};
    return meta;
}

/// --output must name a lossless format: .tif, .tiff or .png.
core::Result<void> checkLosslessOutput(const std::string& output) {
    const std::string ext = std::filesystem::path(output).extension().string();
    if (ext != ".tif" && ext != ".tiff" && ext != ".png" && ext != ".TIF" && ext != ".TIFF" &&
        ext != ".PNG")
        return core::makeError(core::ErrorCode::InvalidArgument,
                               "--output: use .tif, .tiff or .png (lossless), got \"" + output +
                                   "\"");
    return {};
}

} // namespace

CommandRunner addCameraCommand(CLI::App& app) {
    struct Opts {
        std::string config, output;
        std::optional<double> x, y, z;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("camera", "Commission the camera (prints JSON)");
    cmd->add_option("--config", o->config, "Station file (TOML)")->required();
    cmd->require_subcommand(1);
    auto* capture = cmd->add_subcommand("capture", "Capture one frame with the [camera] settings");
    capture
        ->add_option("--output", o->output, "Image file to write (.tif, .tiff or .png: lossless)")
        ->required();
    auto* xo = capture->add_option("--x-um", o->x, "Move the stage to X first, micrometres");
    auto* yo = capture->add_option("--y-um", o->y, "Move the stage to Y first, micrometres");
    capture->add_option("--z-um", o->z, "Target Z, micrometres (default: stay)");
    xo->needs(yo);
    yo->needs(xo);

    return [=]() -> int {
        if (!*cmd)
            return -1;
        const char* name = "camera";
        auto cfg = loadStationConfig(o->config);
        if (!cfg)
            return reportError(name, cfg.error());
        const CameraConfig& cc = cfg->camera;
        if (cc.driver.empty())
            return reportError(name,
                               core::makeError(core::ErrorCode::InvalidArgument,
                                               o->config + ": camera: missing table [camera]"));
        if (auto r = checkLosslessOutput(o->output); !r)
            return reportError(name, r.error());
        // The stage: its position is what a simulated camera looks at, and a move may come first.
        bool stageSimulated = false;
        auto stage = openStage(cfg->stage, stageSimulated);
        if (!stage)
            return reportError(name, stage.error());
        const std::chrono::milliseconds ioTimeout{2000};
        auto here = (*stage)->position(ioTimeout);
        if (!here)
            return reportError(name, here.error());
        hw::StagePosition position = *here;
        if (o->x) {
            hw::StagePosition target{*o->x, *o->y, o->z ? *o->z : position.zUm};
            hw::StageLimits limits = (*stage)->limits();
            if (!o->z)
                limits.z.reset();
            if (auto r = hw::checkWithinLimits(limits, target); !r)
                return reportError(name, r.error());
            auto moved = (*stage)->moveTo(target, cfg->stage.moveTimeout);
            if (!moved)
                return reportError(name, moved.error());
            position = *moved;
        }
        bool simulated = false;
        auto camera = openCamera(
            cc, [&position] { return position; }, simulated);
        if (!camera)
            return reportError(name, camera.error());
        if (simulated)
            std::cerr << "slicectl camera: SIMULATED camera (camera.driver = \"sim\" in "
                      << o->config << ")\n";
        if (stageSimulated)
            std::cerr << "slicectl camera: SIMULATED stage (stage.driver = \"sim\" in " << o->config
                      << ")\n";
        auto used = (*camera)->configure(cc.settings, cc.captureTimeout);
        if (!used)
            return reportError(name, used.error());
        auto frame = (*camera)->capture(cc.captureTimeout);
        if (!frame)
            return reportError(name, frame.error());
        auto mat = toMat(*frame);
        if (!mat)
            return reportError(name, mat.error());
        if (auto w = core::writeImage(o->output, *mat); !w)
            return reportError(name, w.error());
        const nlohmann::json meta = frameJson(*frame);
        nlohmann::json out{
            {"camera", {{"driver", cc.driver}}},
            {"settings_requested", toJson(cc.settings)},
            {"settings_used", toJson(*used)},
            {"frame", meta},
            {"stage_position",
             {{"x_um", position.xUm}, {"y_um", position.yUm}, {"z_um", position.zUm}}},
            {"output", o->output},
            {"simulated", simulated},
            {"stage_simulated", stageSimulated}};
        if (cc.driver == "v4l2")
            out["camera"]["device"] = cc.device;
        if (cc.driver == "libcamera")
            out["camera"]["camera_id"] = cc.cameraId;
        std::cout << out.dump(2) << "\n";
        return 0;
    };
}

} // namespace slicestation::daemon
