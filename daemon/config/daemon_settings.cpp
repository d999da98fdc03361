#include "slicestation/daemon/config/daemon_settings.hpp"

#include "slicestation/daemon/config/config_document.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <fstream>
#include <sstream>

namespace slicestation::daemon {

using core::Result;

namespace {

Result<hw::PixelFormat> pixelFormat(const std::string& s, const FieldReader& rd,
                                    const std::string& field) {
    if (s == "mono8")
        return hw::PixelFormat::Mono8;
    if (s == "mono16")
        return hw::PixelFormat::Mono16;
    if (s == "rgb8")
        return hw::PixelFormat::Rgb8;
    return rd.bad(field, "expected \"mono8\", \"mono16\" or \"rgb8\", got \"" + s + "\"");
}

const char* formatName(hw::PixelFormat f) {
    switch (f) {
    case hw::PixelFormat::Mono8:
        return "mono8";
    case hw::PixelFormat::Mono16:
        return "mono16";
    case hw::PixelFormat::Rgb8:
        return "rgb8";
    }
    return "mono8";
}

std::chrono::milliseconds ms(double s) {
    return std::chrono::milliseconds(std::llround(s * 1000));
}

Result<void> checkObjective(const nlohmann::json& o, const FieldReader& rd, const std::string& op) {
    if (!o.is_object())
        return rd.bad(op, "expected a table");
    return rd.onlyKeys(o, op, {"um_per_px", "camera_to_stage"});
}

// The [scan] table; also the run snapshot, which is the same shape with "objective" expanded.
// The station file (`snapshot` false) is strict: unknown keys refused; a snapshot is this
// program's own record and is read as it was written, so that a stored run always resumes.
/// A station file's [scan]: only known keys, objectives well formed.
Result<void> checkScanTable(const nlohmann::json& t, const FieldReader& rd, const std::string& p) {
    if (auto k = rd.onlyKeys(t, p,
                             {"objective",
                              "objectives",
                              "um_per_px",
                              "format",
                              "width",
                              "height",
                              "exposure_us",
                              "gain",
                              "red_gain",
                              "blue_gain",
                              "autofocus",
                              "focus_range_um",
                              "focus_coarse_step_um",
                              "focus_fine_step_um",
                              "min_tissue_fraction",
                              "start_z_um",
                              "tile_overlap",
                              "move_retries",
                              "capture_retries",
                              "move_timeout_s",
                              "capture_timeout_s",
                              "min_free_mb",
                              "register",
                              "check_atlas_match",
                              "atlas_mismatch_tolerance",
                              "tilted_planes",
                              "max_turn_deg",
                              "count_cells",
                              "cells_channel",
                              "cell_diameter_um",
                              "cells_ontology"});
        !k)
        return k.error();
    if (t.contains("objectives")) {
        const auto& all = t["objectives"];
        const std::string op = FieldReader::join(p, "objectives");
        if (!all.is_object())
            return rd.bad(op, "expected a table of objectives ([scan.objectives.NAME])");
        for (const auto& [name, o] : all.items())
            if (auto c = checkObjective(o, rd, op + "." + name); !c)
                return c.error();
    }
    if (t.contains("objective") && !t["objective"].is_string())
        return rd.bad(FieldReader::join(p, "objective"),
                      "expected the name of a [scan.objectives.NAME] table");
    return {};
}

/// The objective: a name picked from [scan.objectives] or (snapshot) an expanded table; its
/// camera-to-stage mapping a signed permutation.
Result<void> readObjective(const nlohmann::json& t, const FieldReader& rd, const std::string& p,
                           ScanSettings& s) {
    // Objective: either a name picked from [scan.objectives] or (snapshot) an expanded table.
    if (t.contains("objective") && t["objective"].is_object()) {
        const auto& o = t["objective"];
        const std::string op = FieldReader::join(p, "objective");
        auto name = rd.string(o, op, "name", std::nullopt);
        if (!name)
            return name.error();
        s.objective.name = *name;
        auto um = rd.number(o, op, "um_per_px", std::nullopt, 1e-3, 1e4);
        if (!um)
            return um.error();
        s.objective.umPerPx = *um;
        if (o.contains("camera_to_stage")) {
            const auto& m = o["camera_to_stage"];
            if (!m.is_array() || m.size() != 4 ||
                !std::all_of(m.begin(), m.end(), [](auto& v) { return v.is_number(); }))
                return rd.bad(op + ".camera_to_stage", "expected 4 numbers (row-major 2x2)");
            for (int i = 0; i < 4; ++i)
                s.objective.cameraToStage[static_cast<std::size_t>(i)] =
                    m[static_cast<std::size_t>(i)].get<double>();
        }
    } else {
        auto name = rd.string(t, p, "objective", std::string("default"));
        if (!name)
            return name.error();
        s.objective.name = *name;
        const std::string op = FieldReader::join(p, "objectives") + "." + *name;
        const nlohmann::json* o = nullptr;
        if (t.contains("objectives") && t["objectives"].is_object() &&
            t["objectives"].contains(*name))
            o = &t["objectives"][*name];
        if (!o) {
            // No objective table: allow a bare um_per_px in [scan] for a single-objective station.
            auto um = rd.number(t, p, "um_per_px", std::nullopt, 1e-3, 1e4);
            if (!um)
                return rd.bad(op + ".um_per_px",
                              "missing: every objective needs its calibrated pixel size "
                              "(never assumed)");
            s.objective.umPerPx = *um;
        } else {
            auto um = rd.number(*o, op, "um_per_px", std::nullopt, 1e-3, 1e4);
            if (!um)
                return um.error();
            s.objective.umPerPx = *um;
            if (o->contains("camera_to_stage")) {
                const auto& m = (*o)["camera_to_stage"];
                if (!m.is_array() || m.size() != 4 ||
                    !std::all_of(m.begin(), m.end(), [](auto& v) { return v.is_number(); }))
                    return rd.bad(op + ".camera_to_stage", "expected 4 numbers (row-major 2x2)");
                for (std::size_t i = 0; i < 4; ++i)
                    s.objective.cameraToStage[i] = m[i].get<double>();
            }
        }
    }
    const auto& M = s.objective.cameraToStage;
    // Camera axes must lie along stage axes (a signed permutation: identity, flips, 90° turns);
    // frames are then turned into the stage frame exactly, without resampling.
    const auto unit = [](double v) { return std::abs(std::abs(v) - 1) < 1e-9; };
    const auto zero = [](double v) { return std::abs(v) < 1e-9; };
    const bool straight = unit(M[0]) && zero(M[1]) && zero(M[2]) && unit(M[3]);
    const bool swapped = zero(M[0]) && unit(M[1]) && unit(M[2]) && zero(M[3]);
    if (!straight && !swapped)
        return rd.bad(FieldReader::join(p, "objective") + ".camera_to_stage",
                      "must map the camera axes onto the stage axes: entries 0 or +-1, one per row "
                      "and column (e.g. [1, 0, 0, -1] for a flipped Y)");

    return {};
}

/// The camera settings of a run: format, size, exposure, gains.
Result<void> readCameraSettings(const nlohmann::json& t, const FieldReader& rd,
                                const std::string& p, ScanSettings& s) {
    auto fmt = rd.string(t, p, "format", std::string("mono16"));
    if (!fmt)
        return fmt.error();
    auto pf = pixelFormat(*fmt, rd, FieldReader::join(p, "format"));
    if (!pf)
        return pf.error();
    s.camera.format = *pf;
    auto w = rd.integer(t, p, "width", 1280, 16, 65'536);
    if (!w)
        return w.error();
    auto h = rd.integer(t, p, "height", 960, 16, 65'536);
    if (!h)
        return h.error();
    s.camera.width = static_cast<int>(*w);
    s.camera.height = static_cast<int>(*h);
    auto ex = rd.integer(t, p, "exposure_us", 10'000, 1, 60'000'000);
    if (!ex)
        return ex.error();
    s.camera.exposureUs = *ex;
    auto g = rd.number(t, p, "gain", 1.0, 0.1, 1000);
    if (!g)
        return g.error();
    s.camera.analogueGain = *g;
    auto rg = rd.number(t, p, "red_gain", 1.0, 0.01, 100);
    if (!rg)
        return rg.error();
    s.camera.redGain = *rg;
    auto bg = rd.number(t, p, "blue_gain", 1.0, 0.01, 100);
    if (!bg)
        return bg.error();
    s.camera.blueGain = *bg;

    return {};
}

/// How the atlas plane of a section is chosen: matching, its tolerance, tilted planes.
Result<void> readAtlasChoice(const nlohmann::json& t, const FieldReader& rd, const std::string& p,
                             bool snapshot, ScanSettings& s) {
    auto cm = rd.boolean(t, p, "check_atlas_match", true);
    if (!cm)
        return cm.error();
    s.checkAtlasMatch = *cm;
    auto tol = rd.integer(t, p, "atlas_mismatch_tolerance", 2, 0, 1000);
    if (!tol)
        return tol.error();
    s.mismatchToleranceSlices = static_cast<int>(*tol);
    // A snapshot from before the key kept the straight slices it was registered to.
    auto tilted = rd.boolean(t, p, "tilted_planes", !snapshot);
    if (!tilted)
        return tilted.error();
    s.tiltedPlanes = *tilted;
    return {};
}

/// Focus, tiling, retries, timeouts, disk threshold and atlas matching.
Result<void> readRunSettings(const nlohmann::json& t, const FieldReader& rd, const std::string& p,
                             bool snapshot, ScanSettings& s) {
    auto af = rd.boolean(t, p, "autofocus", true);
    if (!af)
        return af.error();
    s.autofocus = *af;
    auto fr = rd.number(t, p, "focus_range_um", 150.0, 1, 5000);
    if (!fr)
        return fr.error();
    s.focusRangeUm = *fr;
    auto fc = rd.number(t, p, "focus_coarse_step_um", 25.0, 0.1, 1000);
    if (!fc)
        return fc.error();
    s.focusCoarseStepUm = *fc;
    auto ff = rd.number(t, p, "focus_fine_step_um", 5.0, 0.05, 1000);
    if (!ff)
        return ff.error();
    if (*ff > *fc)
        return rd.bad(FieldReader::join(p, "focus_fine_step_um"),
                      "must not exceed focus_coarse_step_um");
    s.focusFineStepUm = *ff;
    auto mt = rd.number(t, p, "min_tissue_fraction", 0.03, 0.0, 1.0);
    if (!mt)
        return mt.error();
    s.minTissueFraction = *mt;
    auto sz = rd.number(t, p, "start_z_um", 2'500.0, -1e6, 1e6);
    if (!sz)
        return sz.error();
    s.startZUm = *sz;
    auto ov = rd.number(t, p, "tile_overlap", 0.1, 0.0, 0.5);
    if (!ov)
        return ov.error();
    s.tileOverlap = *ov;
    auto mr = rd.integer(t, p, "move_retries", 2, 0, 10);
    if (!mr)
        return mr.error();
    s.moveRetries = static_cast<int>(*mr);
    auto cr = rd.integer(t, p, "capture_retries", 2, 0, 10);
    if (!cr)
        return cr.error();
    s.captureRetries = static_cast<int>(*cr);
    auto mto = rd.number(t, p, "move_timeout_s", 10.0, 0.01, 600);
    if (!mto)
        return mto.error();
    s.moveTimeout = ms(*mto);
    auto cto = rd.number(t, p, "capture_timeout_s", 5.0, 0.01, 600);
    if (!cto)
        return cto.error();
    s.captureTimeout = ms(*cto);
    auto mf = rd.number(t, p, "min_free_mb", 500.0, 0, 1e9);
    if (!mf)
        return mf.error();
    s.minFreeBytes = static_cast<std::uint64_t>(*mf * 1024 * 1024);
    auto reg = rd.boolean(t, p, "register", true);
    if (!reg)
        return reg.error();
    // Nothing skips registration yet (the scanner waits for every capture to be registered):
    // refused rather than stored and ignored. A snapshot keeps what an older version stored.
    if (!*reg && !snapshot)
        return rd.bad(
            FieldReader::join(p, "register"),
            "false is not supported: every captured section is registered; remove the key");
    if (auto a = readAtlasChoice(t, rd, p, snapshot, s); !a)
        return a.error();
    auto turn = rd.number(t, p, "max_turn_deg", 180.0, 0, 180);
    if (!turn)
        return turn.error();
    s.maxTurnDeg = *turn;
    if (snapshot) { // the station file has it in [damage] (readDamage)
        auto fs = rd.number(t, p, "damage_flag_score", 0.5, 0, 1);
        if (!fs)
            return fs.error();
        s.damageFlagScore = *fs;
    }
    // Cells per region after registration (docs/cells.md); off unless asked for.
    auto cc = rd.boolean(t, p, "count_cells", false);
    if (!cc)
        return cc.error();
    s.countCells = *cc;
    auto ch = rd.integer(t, p, "cells_channel", -1, -1, 3);
    if (!ch)
        return ch.error();
    s.cellsChannel = static_cast<int>(*ch);
    auto cd = rd.number(t, p, "cell_diameter_um", 15.0, 1, 500);
    if (!cd)
        return cd.error();
    s.cellDiameterUm = *cd;
    auto co = rd.string(t, p, "cells_ontology", std::string());
    if (!co)
        return co.error();
    s.cellsOntology = *co;
    return {};
}

Result<ScanSettings> readScan(const nlohmann::json& scan, const FieldReader& rd,
                              const std::string& p, bool snapshot) {
    ScanSettings s;
    const nlohmann::json empty = nlohmann::json::object();
    const nlohmann::json& t = scan.is_object() ? scan : empty;
    if (!snapshot)
        if (auto r = checkScanTable(t, rd, p); !r)
            return r.error();
    if (auto r = readObjective(t, rd, p, s); !r)
        return r.error();
    if (auto r = readCameraSettings(t, rd, p, s); !r)
        return r.error();
    if (auto r = readRunSettings(t, rd, p, snapshot, s); !r)
        return r.error();
    return s;
}

} // namespace

Result<DaemonSettings> parseDaemonSettings(const nlohmann::json& station,
                                           const std::string& origin) {
    FieldReader rd(origin);
    DaemonSettings d;
    if (!station.is_object())
        return rd.bad("(document)", "expected a table at the top");
    if (auto k = rd.onlyKeys(station, "(document)", kStationTables); !k)
        return k.error();
    const nlohmann::json empty = nlohmann::json::object();
    const nlohmann::json& t = station.contains("daemon") ? station["daemon"] : empty;
    if (!t.is_object())
        return rd.bad("daemon", "expected a table");
    if (auto k = rd.onlyKeys(t, "daemon",
                             {"state_dir", "atlas", "builtin_interval_um", "http_bind", "http_port",
                              "token", "token_file", "watchdog_stall_s"});
        !k)
        return k.error();
    auto sd = rd.string(t, "daemon", "state_dir", std::string());
    if (!sd)
        return sd.error();
    d.stateDir = *sd;
    auto atlas = rd.string(t, "daemon", "atlas", std::string("builtin"));
    if (!atlas)
        return atlas.error();
    d.atlas = *atlas;
    auto bi = rd.number(t, "daemon", "builtin_interval_um", 100.0, 10, 4000);
    if (!bi)
        return bi.error();
    d.builtinIntervalUm = *bi;
    auto bind = rd.string(t, "daemon", "http_bind", std::string("127.0.0.1"));
    if (!bind)
        return bind.error();
    d.httpBind = *bind;
    auto port = rd.integer(t, "daemon", "http_port", 8470, 0, 65535);
    if (!port)
        return port.error();
    d.httpPort = static_cast<int>(*port);
    auto token = rd.string(t, "daemon", "token", std::string());
    if (!token)
        return token.error();
    d.token = *token;
    if (t.contains("token_file")) {
        if (!d.token.empty())
            return rd.bad("daemon.token_file", "give token or token_file, not both");
        auto tf = rd.string(t, "daemon", "token_file", std::nullopt);
        if (!tf)
            return tf.error();
        std::ifstream in(*tf);
        if (!in)
            return rd.bad("daemon.token_file", "cannot read " + *tf);
        std::string head(kMaxTokenBytes + 2, '\0'); // the first line, bounded
        in.read(head.data(), static_cast<std::streamsize>(head.size()));
        head.resize(static_cast<std::size_t>(in.gcount()));
        d.token = head.substr(0, head.find('\n'));
        while (!d.token.empty() && std::isspace(static_cast<unsigned char>(d.token.back())))
            d.token.pop_back();
        if (d.token.empty())
            return rd.bad("daemon.token_file", *tf + " is empty");
    }
    if (!d.token.empty() && d.token.size() < 16)
        return rd.bad("daemon.token", "too short: use at least 16 characters");
    if (d.token.size() > kMaxTokenBytes)
        return rd.bad("daemon.token", "longer than " + std::to_string(kMaxTokenBytes) + " bytes");
    for (const char c : d.token)
        if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f)
            return rd.bad("daemon.token", "must not contain control characters");
    auto ws = rd.number(t, "daemon", "watchdog_stall_s", 120.0, 1, 86'400);
    if (!ws)
        return ws.error();
    d.watchdogStall = std::chrono::seconds(std::llround(*ws));
    const nlohmann::json& scan = station.contains("scan") ? station["scan"] : empty;
    if (!scan.is_object())
        return rd.bad("scan", "expected a table");
    auto s = readScan(scan, rd, "scan", false);
    if (!s)
        return s.error();
    d.scan = *s;
    const nlohmann::json& damage = station.contains("damage") ? station["damage"] : empty;
    if (!damage.is_object())
        return rd.bad("damage", "expected a table");
    if (auto k = rd.onlyKeys(damage, "damage", {"flag_score"}); !k)
        return k.error();
    auto fs = rd.number(damage, "damage", "flag_score", 0.5, 0, 1);
    if (!fs)
        return fs.error();
    d.scan.damageFlagScore = *fs;
    return d;
}

nlohmann::json toJson(const ScanSettings& s) {
    const auto& M = s.objective.cameraToStage;
    return {{"objective",
             {{"name", s.objective.name},
              {"um_per_px", s.objective.umPerPx},
              {"camera_to_stage", {M[0], M[1], M[2], M[3]}}}},
            {"format", formatName(s.camera.format)},
            {"width", s.camera.width},
            {"height", s.camera.height},
            {"exposure_us", s.camera.exposureUs},
            {"gain", s.camera.analogueGain},
            {"red_gain", s.camera.redGain},
            {"blue_gain", s.camera.blueGain},
            {"autofocus", s.autofocus},
            {"focus_range_um", s.focusRangeUm},
            {"focus_coarse_step_um", s.focusCoarseStepUm},
            {"focus_fine_step_um", s.focusFineStepUm},
            {"min_tissue_fraction", s.minTissueFraction},
            {"start_z_um", s.startZUm},
            {"tile_overlap", s.tileOverlap},
            {"move_retries", s.moveRetries},
            {"capture_retries", s.captureRetries},
            {"move_timeout_s", s.moveTimeout.count() / 1000.0},
            {"capture_timeout_s", s.captureTimeout.count() / 1000.0},
            {"min_free_mb", static_cast<double>(s.minFreeBytes) / (1024.0 * 1024.0)},
            {"check_atlas_match", s.checkAtlasMatch},
            {"atlas_mismatch_tolerance", s.mismatchToleranceSlices},
            {"tilted_planes", s.tiltedPlanes},
            {"max_turn_deg", s.maxTurnDeg},
            {"damage_flag_score", s.damageFlagScore},
            {"count_cells", s.countCells},
            {"cells_channel", s.cellsChannel},
            {"cell_diameter_um", s.cellDiameterUm},
            {"cells_ontology", s.cellsOntology}};
}

Result<ScanSettings> scanSettingsFromJson(const nlohmann::json& j, const std::string& origin) {
    FieldReader rd(origin);
    if (!j.is_object())
        return rd.bad("settings", "the run's settings snapshot is not an object");
    return readScan(j, rd, "settings", true);
}

} // namespace slicestation::daemon
