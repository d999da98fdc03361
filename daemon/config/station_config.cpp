#include "slicestation/daemon/config/station_config.hpp"

#include "slicestation/drivers/libcamera_camera.hpp"
#include "slicestation/drivers/v4l2_camera.hpp"
#include "slicestation/sim/faulty_camera.hpp"

#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <string_view>
#include <fstream>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

using Json = nlohmann::json;

// The station file is read through parseDocument (size, depth and number limits) and
// FieldReader (strict keys); `prefix` ends in a dot ("stage.axes.x.").
struct Reader {
    std::string origin;
    FieldReader fields{origin};
    core::Error bad(const std::string& key, const std::string& what) const {
        return makeError(ErrorCode::InvalidArgument, origin + ": " + key + ": " + what);
    }
    static std::string path(const std::string& prefix) {
        return prefix.empty() ? prefix : prefix.substr(0, prefix.size() - 1);
    }
    core::Result<double> number(const Json& t, const std::string& prefix, const char* key,
                                std::optional<double> fallback, double min = -1e300, double max = 1e300) const {
        if (!t.contains(key)) {
            if (fallback) return *fallback;
            return bad(prefix + key, "missing");
        }
        const Json& v = t[key];
        if (!v.is_number()) return bad(prefix + key, "expected a number");
        const double d = v.get<double>();
        if (!std::isfinite(d)) return bad(prefix + key, "expected a number");
        if (d < min) return bad(prefix + key, "must be >= " + shortNumber(min));
        if (d > max) return bad(prefix + key, "must be <= " + shortNumber(max));
        return d;
    }
    core::Result<std::string> string(const Json& t, const std::string& prefix, const char* key,
                                     std::optional<std::string> fallback) const {
        if (!t.contains(key)) {
            if (fallback) return *fallback;
            return bad(prefix + key, "missing");
        }
        if (!t[key].is_string()) return bad(prefix + key, "expected a string");
        return t[key].get<std::string>();
    }
    /// Strict keys: a typo is refused with the nearest known key; a key of another driver or
    /// transport (`others`) is refused as such, not silently ignored.
    core::Result<void> keys(const Json& t, const std::string& prefix, std::initializer_list<std::string_view> known,
                            std::initializer_list<std::string_view> others = {}, const std::string& only = "") const {
        for (const auto o : others)
            if (t.contains(o)) return bad(prefix + std::string(o), "only for " + only);
        return fields.onlyKeys(t, path(prefix), known);
    }
    static std::string shortNumber(double v) {
        std::ostringstream os;
        os << v;
        return os.str();
    }
};

const Json* table(const Json& t, const char* key) {
    return t.contains(key) && t[key].is_object() ? &t[key] : nullptr;
}

core::Result<bool> boolean(const Json& t, const std::string& key, bool fallback, const Reader& rd) {
    if (!t.contains(key)) return fallback;
    if (!t[key].is_boolean()) return rd.bad(key, "expected true or false");
    return t[key].get<bool>();
}

core::Result<int> integer(const Reader& rd, const Json& t, const std::string& prefix, const char* key,
                          int fallback, int min, int max) {
    auto v = rd.number(t, prefix, key, double(fallback));
    if (!v) return v.error();
    if (std::floor(*v) != *v || *v < min || *v > max)
        return rd.bad(prefix + key, "must be an integer " + std::to_string(min) + ".." + std::to_string(max));
    return static_cast<int>(*v);
}

/// [stage]: the keys of its driver and transport only (a key of another names it).
core::Result<void> checkStageKeys(const Json& st, const Reader& rd, const std::string& driver) {
    const std::string p = "stage.";
    if (driver == "sim") {
        if (auto k = rd.keys(st, p,
                             {"driver", "move_timeout_s", "home_timeout_s", "axes", "speed_um_per_s",
                              "accel_um_per_s2", "position_window_um", "settle_ms"},
                             {"response_timeout_ms", "retries", "transport", "host", "port", "device", "baud",
                              "parity", "data_bits", "stop_bits", "map", "preset"},
                             "driver = \"modbus\"");
            !k)
            return k.error();
    } else {
        const bool tcp = st.contains("transport") && st["transport"] == "tcp";
        const std::initializer_list<std::string_view> common = {
            "driver", "move_timeout_s", "home_timeout_s", "axes", "speed_um_per_s", "accel_um_per_s2",
            "position_window_um", "settle_ms", "response_timeout_ms", "retries", "transport", "map",
            "preset", "host", "port", "device", "baud", "parity", "data_bits", "stop_bits"};
        auto k = tcp ? rd.keys(st, p, common, {"device", "baud", "parity", "data_bits", "stop_bits"},
                               "transport = \"rtu\"")
                     : rd.keys(st, p, common, {"host", "port"}, "transport = \"tcp\"");
        if (!k) return k.error();
        if (st.contains("map") && st.contains("preset"))
            return rd.bad("stage.map", "give map or preset, not both");
    }
    return {};
}

/// [stage.axes.x], [stage.axes.y] and an optional [stage.axes.z].
core::Result<std::vector<drivers::ModbusAxisConfig>> readAxes(const Json& st, const Reader& rd,
                                                              const std::string& driver) {
    // Axes: [stage.axes.x], [stage.axes.y], optional [stage.axes.z].
    const Json* axes = table(st, "axes");
    if (!axes) return rd.bad("stage.axes", "missing table (needs [stage.axes.x] and [stage.axes.y])");
    if (auto k = rd.keys(*axes, "stage.axes.", {"x", "y", "z"}); !k) return k.error();
    std::vector<drivers::ModbusAxisConfig> list;
    for (const char* name : {"x", "y", "z"}) {
        const Json* a = table(*axes, name);
        const std::string ap = "stage.axes." + std::string(name) + ".";
        if (!a) {
            if (std::string(name) == "z" && !axes->contains("z")) continue;
            return rd.bad("stage.axes." + std::string(name), "missing table");
        }
        if (auto k = driver == "modbus"
                         ? rd.keys(*a, ap, {"min_um", "max_um", "slave", "steps_per_um"})
                         : rd.keys(*a, ap, {"min_um", "max_um"}, {"slave", "steps_per_um"}, "driver = \"modbus\"");
            !k)
            return k.error();
        drivers::ModbusAxisConfig ax;
        ax.name = name;
        auto mn = rd.number(*a, ap, "min_um", std::nullopt, -1e7, 1e7);
        if (!mn) return mn.error();
        auto mx = rd.number(*a, ap, "max_um", std::nullopt, -1e7, 1e7);
        if (!mx) return mx.error();
        if (!(*mn < *mx)) return rd.bad(ap + "max_um", "must be greater than min_um");
        ax.minUm = *mn;
        ax.maxUm = *mx;
        if (driver == "modbus") {
            auto slave = rd.number(*a, ap, "slave", std::nullopt, 1, 247);
            if (!slave) return slave.error();
            if (*slave > 247 || std::floor(*slave) != *slave) return rd.bad(ap + "slave", "must be an integer 1..247");
            ax.slave = static_cast<int>(*slave);
            auto spu = rd.number(*a, ap, "steps_per_um", std::nullopt, 1e-9, 1e6);
            if (!spu) return spu.error();
            ax.stepsPerUm = *spu;
        }
        list.push_back(ax);
    }
    return list;
}

/// The Modbus link: TCP or RTU settings, and the register map (a file or a preset).
core::Result<void> readModbusLink(const Json& st, const Reader& rd, drivers::ModbusStageConfig& m) {
    const std::string p = "stage.";
    auto transport = rd.string(st, p, "transport", std::nullopt);
    if (!transport) return transport.error();
    if (*transport == "tcp") {
        m.transport = drivers::ModbusStageConfig::Transport::Tcp;
        auto host = rd.string(st, p, "host", std::nullopt);
        if (!host) return host.error();
        m.host = *host;
        auto port = integer(rd, st, p, "port", 502, 1, 65535);
        if (!port) return port.error();
        m.port = *port;
    } else if (*transport == "rtu") {
        m.transport = drivers::ModbusStageConfig::Transport::Rtu;
        auto dev = rd.string(st, p, "device", std::nullopt);
        if (!dev) return dev.error();
        m.device = *dev;
        auto baud = integer(rd, st, p, "baud", 115200, 50, 4'000'000);
        if (!baud) return baud.error();
        m.baud = *baud;
        auto parity = rd.string(st, p, "parity", std::string("E"));
        if (!parity) return parity.error();
        if (*parity != "N" && *parity != "E" && *parity != "O") return rd.bad("stage.parity", "expected \"N\", \"E\" or \"O\"");
        m.parity = (*parity)[0];
        auto db = integer(rd, st, p, "data_bits", 8, 5, 8);
        if (!db) return db.error();
        m.dataBits = *db;
        auto sb = integer(rd, st, p, "stop_bits", 1, 1, 2);
        if (!sb) return sb.error();
        m.stopBits = *sb;
    } else {
        return rd.bad("stage.transport", "expected \"tcp\" or \"rtu\"");
    }

    if (st.contains("map")) {
        auto file = rd.string(st, p, "map", std::nullopt);
        if (!file) return file.error();
        std::filesystem::path f = *file;
        if (f.is_relative()) f = std::filesystem::path(rd.origin).parent_path() / f;
        auto map = drivers::loadRegisterMap(f);
        if (!map) return makeError(map.error().code, rd.origin + ": stage.map: " + map.error().message);
        m.map = std::move(*map);
    } else {
        auto preset = rd.string(st, p, "preset", std::string("oriental-az"));
        if (!preset) return preset.error();
        auto map = drivers::presetMap(*preset);
        if (!map) return rd.bad("stage.preset", map.error().message);
        m.map = std::move(*map);
    }
    return {};
}

core::Result<StageConfig> parseStage(const Json& st, const Reader& rd) {
    StageConfig c;
    const std::string p = "stage.";
    auto driver = rd.string(st, p, "driver", std::nullopt);
    if (!driver) return driver.error();
    c.driver = *driver;
    if (c.driver != "modbus" && c.driver != "sim")
        return rd.bad("stage.driver", "expected \"modbus\" or \"sim\", got \"" + c.driver + "\"");
    if (auto k = checkStageKeys(st, rd, c.driver); !k) return k.error();
    auto ms = [](double s) { return std::chrono::milliseconds(std::llround(s * 1000)); };
    auto mt = rd.number(st, p, "move_timeout_s", 10.0, 0.001, 3600);
    if (!mt) return mt.error();
    c.moveTimeout = ms(*mt);
    auto ht = rd.number(st, p, "home_timeout_s", 60.0, 0.001, 3600);
    if (!ht) return ht.error();
    c.homeTimeout = ms(*ht);

    auto axes = readAxes(st, rd, c.driver);
    if (!axes) return axes.error();
    const std::vector<drivers::ModbusAxisConfig>& list = *axes;
    auto speed = rd.number(st, p, "speed_um_per_s", 10'000.0, 1e-6, 1e7);
    if (!speed) return speed.error();
    auto accel = rd.number(st, p, "accel_um_per_s2", 50'000.0, 1e-6, 1e9);
    if (!accel) return accel.error();
    auto window = rd.number(st, p, "position_window_um", 1.0, 1e-6, 1e5);
    if (!window) return window.error();
    auto settle = rd.number(st, p, "settle_ms", 50.0, 0, 60'000);
    if (!settle) return settle.error();

    if (c.driver == "sim") {
        c.sim.limits.x = {list[0].minUm, list[0].maxUm};
        c.sim.limits.y = {list[1].minUm, list[1].maxUm};
        c.sim.limits.z = list.size() > 2 ? std::optional<hw::AxisRange>({list[2].minUm, list[2].maxUm}) : std::nullopt;
        c.sim.speedUmPerS = *speed;
        c.sim.accelUmPerS2 = *accel;
        c.sim.positionWindowUm = *window;
        c.sim.settle = std::chrono::milliseconds(std::llround(*settle));
        return c;
    }
    auto& m = c.modbus;
    m.axes = list;
    m.speedUmPerS = *speed;
    m.accelUmPerS2 = *accel;
    m.positionWindowUm = *window;
    m.settle = std::chrono::milliseconds(std::llround(*settle));
    auto rto = rd.number(st, p, "response_timeout_ms", 200.0, 1, 60'000);
    if (!rto) return rto.error();
    m.responseTimeout = std::chrono::milliseconds(std::llround(*rto));
    auto retries = integer(rd, st, p, "retries", 2, 0, 100);
    if (!retries) return retries.error();
    m.retries = *retries;

    if (auto l = readModbusLink(st, rd, m); !l) return l.error();
    return c;
}

/// [camera.sim]: the sections on the virtual slide, real images or generated sections (default:
/// four, front to back, one torn).
core::Result<void> readSimSlideContent(const Json& t, const Reader& rd, const std::string& p, SimCameraSection& c) {
    auto& sl = c.slide;
    if (t.contains("images")) {
        const Json* a = &t["images"];
        if (!a->is_array() || a->empty()) return rd.bad(p + "images", "expected a non-empty array of file names");
        if (a->size() > kMaxSimSections)
            return rd.bad(p + "images", "at most " + std::to_string(kMaxSimSections) + " images");
        for (std::size_t i = 0; i < a->size(); ++i) {
            if (!(*a)[i].is_string()) return rd.bad(p + "images[" + std::to_string(i) + "]", "expected a file name");
            std::filesystem::path f = (*a)[i].get<std::string>();
            if (f.is_relative()) f = std::filesystem::path(rd.origin).parent_path() / f;
            c.images.push_back(f);
        }
        if (t.contains("sections")) return rd.bad(p + "sections", "give either images or sections, not both");
    } else if (t.contains("sections")) {
        const Json* a = &t["sections"];
        if (!a->is_array() || a->empty() ||
            !std::all_of(a->begin(), a->end(), [](const Json& e) { return e.is_object(); }))
            return rd.bad(p + "sections", "expected [[camera.sim.sections]] tables");
        if (a->size() > kMaxSimSections)
            return rd.bad(p + "sections", "at most " + std::to_string(kMaxSimSections) + " sections");
        for (std::size_t i = 0; i < a->size(); ++i) {
            const Json& st = (*a)[i];
            const std::string sp = p + "sections[" + std::to_string(i) + "].";
            if (auto k = rd.keys(st, sp, {"ap_fraction", "damage", "seed"}); !k) return k.error();
            sim::SlideSectionSpec spec;
            auto ap = rd.number(st, sp, "ap_fraction", std::nullopt, 0);
            if (!ap) return ap.error();
            if (*ap > 1) return rd.bad(sp + "ap_fraction", "must be in [0, 1]");
            spec.apFraction = *ap;
            auto dmg = rd.string(st, sp, "damage", std::string());
            if (!dmg) return dmg.error();
            if (*dmg != "" && *dmg != "tear" && *dmg != "missing" && *dmg != "fragment")
                return rd.bad(sp + "damage", "expected \"\", \"tear\", \"missing\" or \"fragment\", got \"" + *dmg + "\"");
            spec.damage = *dmg;
            auto seed = integer(rd, st, sp, "seed", static_cast<int>(i + 1), 0, 2'147'483'647);
            if (!seed) return seed.error();
            spec.seed = static_cast<std::uint64_t>(*seed);
            sl.sections.push_back(spec);
        }
    } else { // a default slide: four sections front to back, one torn
        sl.sections = {{0.2, "", 1}, {0.4, "tear", 2}, {0.6, "", 3}, {0.8, "missing", 4}};
    }
    return {};
}

/// The slide is one image in memory: bounded before it is allocated.
core::Result<void> checkSimSlideSize(const SimCameraSection& c, const Reader& rd, const std::string& p) {
    const auto& sl = c.slide;
    // The slide is one image in memory: bounded before it is allocated (generated slides carry
    // a margin; loaded ones are a grid of pitch-sized cells).
    const double n = static_cast<double>(c.images.empty() ? sl.sections.size() : c.images.size());
    const double gridCols = std::min<double>(sl.columns, n), gridRows = std::ceil(n / sl.columns);
    const double pxUm = c.images.empty() ? sl.umPerPx : c.imagesUmPerPx;
    const double margin = c.images.empty() ? 2 * sl.marginUm : 0;
    const double wPx = (gridCols * sl.sectionPitchUm + margin) / pxUm;
    const double hPx = (gridRows * sl.sectionPitchUm + margin) / pxUm;
    if (wPx > kMaxSimSlideSidePx || hPx > kMaxSimSlideSidePx || wPx * hPx > kMaxSimSlidePixels) {
        std::ostringstream os;
        os << "the virtual slide would be " << std::llround(wPx) << " x " << std::llround(hPx)
           << " px (at most " << kMaxSimSlideSidePx << " a side and " << kMaxSimSlidePixels
           << " in all): raise " << (c.images.empty() ? "slide_um_per_px" : "images_um_per_px")
           << " or lower section_pitch_um, margin_um or the number of sections";
        return rd.bad(p + "section_pitch_um", os.str());
    }
    return {};
}

core::Result<SimCameraSection> parseSimCamera(const Json& t, const Reader& rd) {
    SimCameraSection c;
    const std::string p = "camera.sim.";
    if (auto k = rd.keys(t, p,
                         {"sensor_um_per_px", "focus_z_um", "focus_tilt_x", "focus_tilt_y", "blur_sigma_px_per_um",
                          "slide_um_per_px", "slide_origin_x_um", "slide_origin_y_um", "section_pitch_um",
                          "section_width_um", "margin_um", "images_um_per_px", "columns", "brightfield",
                          "timeout_first_captures", "disconnect_after_frames", "images", "sections"});
        !k)
        return k.error();
    struct Num {
        const char* key;
        double* target;
        double min;
        double max;
    };
    auto& sl = c.slide;
    for (const Num& n : {Num{"sensor_um_per_px", &c.sensorUmPerPx, 1e-3, 1e4}, Num{"focus_z_um", &c.focusZUm, -1e6, 1e6},
                         Num{"focus_tilt_x", &c.focusTiltX, -10, 10}, Num{"focus_tilt_y", &c.focusTiltY, -10, 10},
                         Num{"blur_sigma_px_per_um", &c.blurSigmaPxPerUm, 0, 100},
                         Num{"slide_um_per_px", &sl.umPerPx, 0.1, 1e4},
                         Num{"slide_origin_x_um", &sl.originXUm, -1e7, 1e7}, Num{"slide_origin_y_um", &sl.originYUm, -1e7, 1e7},
                         Num{"section_pitch_um", &sl.sectionPitchUm, 1e-3, 1e6},
                         Num{"section_width_um", &sl.sectionWidthUm, 1e-3, 1e6}, Num{"margin_um", &sl.marginUm, 0, 1e6},
                         Num{"images_um_per_px", &c.imagesUmPerPx, 0.1, 1e4}}) {
        auto v = rd.number(t, p, n.key, *n.target, n.min, n.max);
        if (!v) return v.error();
        *n.target = *v;
    }
    if (sl.sectionWidthUm > sl.sectionPitchUm) return rd.bad(p + "section_width_um", "must not exceed section_pitch_um");
    auto cols = integer(rd, t, p, "columns", sl.columns, 1, 1000);
    if (!cols) return cols.error();
    sl.columns = *cols;
    auto bf = boolean(t, "brightfield", false, rd);
    if (!bf) return rd.bad(p + "brightfield", "expected true or false");
    sl.brightfield = *bf;
    auto to = integer(rd, t, p, "timeout_first_captures", 0, 0, 1'000'000);
    if (!to) return to.error();
    c.timeoutFirstCaptures = *to;
    auto dc = integer(rd, t, p, "disconnect_after_frames", -1, -1, 1'000'000'000);
    if (!dc) return dc.error();
    c.disconnectAfterFrames = *dc;

    if (auto r = readSimSlideContent(t, rd, p, c); !r) return r.error();
    if (auto r = checkSimSlideSize(c, rd, p); !r) return r.error();
    return c;
}

core::Result<CameraConfig> parseCamera(const Json& t, const Reader& rd) {
    CameraConfig c;
    const std::string p = "camera.";
    auto driver = rd.string(t, p, "driver", std::nullopt);
    if (!driver) return driver.error();
    c.driver = *driver;
    if (c.driver != "v4l2" && c.driver != "libcamera" && c.driver != "sim")
        return rd.bad("camera.driver", "expected \"v4l2\", \"libcamera\" or \"sim\", got \"" + c.driver + "\"");
    {
        const std::initializer_list<std::string_view> known = {
            "driver", "device", "camera_id", "format", "width", "height", "exposure_us", "gain",
            "red_gain", "blue_gain", "capture_timeout_s", "settle_frames", "sim"};
        // A key of another driver is refused as such, not ignored.
        for (const auto& [key, owner] : {std::pair{"device", "v4l2"}, std::pair{"camera_id", "libcamera"},
                                          std::pair{"sim", "sim"}})
            if (t.contains(key) && c.driver != owner)
                return rd.bad(p + key, std::string("only for driver = \"") + owner + "\"");
        if (auto k = rd.keys(t, p, known); !k) return k.error();
    }
    auto device = rd.string(t, p, "device", c.device);
    if (!device) return device.error();
    c.device = *device;
    auto id = rd.string(t, p, "camera_id", std::string());
    if (!id) return id.error();
    c.cameraId = *id;
    auto fmt = rd.string(t, p, "format", std::string("mono8"));
    if (!fmt) return fmt.error();
    if (*fmt == "mono8") c.settings.format = hw::PixelFormat::Mono8;
    else if (*fmt == "mono16") c.settings.format = hw::PixelFormat::Mono16;
    else if (*fmt == "rgb8") c.settings.format = hw::PixelFormat::Rgb8;
    else return rd.bad("camera.format", "expected \"mono8\", \"mono16\" or \"rgb8\", got \"" + *fmt + "\"");
    auto w = integer(rd, t, p, "width", 1024, 16, 16384);
    if (!w) return w.error();
    auto h = integer(rd, t, p, "height", 768, 16, 16384);
    if (!h) return h.error();
    c.settings.width = *w;
    c.settings.height = *h;
    auto exp = rd.number(t, p, "exposure_us", 10'000.0, 1);
    if (!exp) return exp.error();
    if (*exp > 10'000'000) return rd.bad("camera.exposure_us", "must be 1..10000000");
    c.settings.exposureUs = std::llround(*exp);
    auto gain = rd.number(t, p, "gain", 1.0, 1e-6, 1000);
    if (!gain) return gain.error();
    c.settings.analogueGain = *gain;
    auto rg = rd.number(t, p, "red_gain", 1.0, 1e-6, 100);
    if (!rg) return rg.error();
    auto bg = rd.number(t, p, "blue_gain", 1.0, 1e-6, 100);
    if (!bg) return bg.error();
    c.settings.redGain = *rg;
    c.settings.blueGain = *bg;
    auto ct = rd.number(t, p, "capture_timeout_s", 5.0, 0.001, 600);
    if (!ct) return ct.error();
    c.captureTimeout = std::chrono::milliseconds(std::llround(*ct * 1000));
    auto settle = integer(rd, t, p, "settle_frames", 3, 0, 100);
    if (!settle) return settle.error();
    c.settleFrames = *settle;
    if (c.driver == "sim") {
        static const Json empty = Json::object();
        if (t.contains("sim") && !t["sim"].is_object()) return rd.bad("camera.sim", "expected a table");
        const Json* st = table(t, "sim");
        auto s = parseSimCamera(st ? *st : empty, rd);
        if (!s) return s.error();
        c.sim = std::move(*s);
    }
    return c;
}

} // namespace

namespace {

core::Result<StationConfig> stationFromDocument(const Json& root, const std::filesystem::path& origin) {
    Reader rd{origin.string()};
    if (auto k = rd.fields.onlyKeys(root, "(document)", kStationTables); !k) return k.error();
    StationConfig cfg;
    cfg.file = origin;
    const Json* st = table(root, "stage");
    if (!st) return rd.bad("stage", "missing table [stage]");
    auto stage = parseStage(*st, rd);
    if (!stage) return stage.error();
    cfg.stage = std::move(*stage);
    if (root.contains("camera")) {
        if (!root["camera"].is_object()) return rd.bad("camera", "expected a table [camera]");
        auto c = parseCamera(root["camera"], rd);
        if (!c) return c.error();
        cfg.camera = std::move(*c);
    }
    return cfg;
}

} // namespace

core::Result<StationConfig> parseStationConfig(std::string_view text, const std::filesystem::path& origin) {
    auto doc = parseDocument(text, DocumentFormat::Toml, origin.string());
    if (!doc) return doc.error();
    return stationFromDocument(*doc, origin);
}

core::Result<StationConfig> loadStationConfig(const std::filesystem::path& file) {
    std::error_code ec;
    if (!std::filesystem::exists(file, ec))
        return makeError(ErrorCode::NotFound, "station file " + file.string() + " cannot be opened");
    auto doc = readDocument(file); // bounded in size, like every document
    if (!doc) return doc.error();
    return stationFromDocument(*doc, file);
}

core::Result<std::unique_ptr<hw::Stage>> openStage(const StageConfig& config, bool& simulated) {
    simulated = config.driver == "sim";
    if (simulated) {
        auto s = sim::SimStage::create(config.sim);
        if (!s) return s.error();
        return std::unique_ptr<hw::Stage>(std::move(s).value());
    }
    auto s = drivers::ModbusStage::create(config.modbus);
    if (!s) return s.error();
    return std::unique_ptr<hw::Stage>(std::move(s).value());
}

} // namespace slicestation::daemon

namespace slicestation::daemon {

core::Result<std::unique_ptr<hw::Camera>> openCamera(const CameraConfig& config,
                                                     std::function<hw::StagePosition()> stagePosition,
                                                     bool& simulated) {
    simulated = config.driver == "sim";
    if (config.driver.empty())
        return makeError(ErrorCode::InvalidArgument, "camera: the station file has no [camera] section");
    if (config.driver == "v4l2") {
        drivers::V4l2CameraConfig c;
        c.device = config.device;
        c.settleFrames = config.settleFrames;
        auto cam = drivers::V4l2Camera::create(c);
        if (!cam) return cam.error();
        return std::unique_ptr<hw::Camera>(std::move(cam).value());
    }
    if (config.driver == "libcamera") {
        drivers::LibcameraCameraConfig c;
        c.cameraId = config.cameraId;
        c.settleFrames = config.settleFrames;
        auto cam = drivers::LibcameraCamera::create(c);
        if (!cam) return cam.error();
        return std::unique_ptr<hw::Camera>(std::move(cam).value());
    }
    if (!stagePosition)
        return makeError(ErrorCode::InvalidArgument, "camera: the simulated camera needs the stage position");
    const auto& s = config.sim;
    auto slide = s.images.empty() ? sim::makeVirtualSlide(s.slide)
                                  : sim::loadVirtualSlide(s.images, s.imagesUmPerPx, s.slide.columns, s.slide.sectionPitchUm);
    if (!slide) return makeError(slide.error().code, "camera.sim: " + slide.error().message, slide.error().sysErrno);
    if (!s.images.empty()) { // loaded slides start at (0, 0); the configured origin moves them
        slide->originXUm = s.slide.originXUm;
        slide->originYUm = s.slide.originYUm;
        for (auto& sec : slide->sections) {
            sec.centre.xUm += s.slide.originXUm;
            sec.centre.yUm += s.slide.originYUm;
        }
    }
    sim::SimCameraConfig cc;
    cc.sensorUmPerPx = s.sensorUmPerPx;
    cc.stagePosition = std::move(stagePosition);
    cc.focusZUm = s.focusZUm;
    cc.focusTiltX = s.focusTiltX;
    cc.focusTiltY = s.focusTiltY;
    cc.blurSigmaPxPerUm = s.blurSigmaPxPerUm;
    auto cam = sim::SimCamera::create(*slide, std::move(cc));
    if (!cam) return cam.error();
    if (s.timeoutFirstCaptures == 0 && s.disconnectAfterFrames < 0)
        return std::unique_ptr<hw::Camera>(std::move(cam).value());
    auto faulty = sim::FaultyCamera::create(std::move(cam).value(), std::make_shared<core::SteadyClock>());
    if (!faulty) return faulty.error();
    (*faulty)->timeoutNext(s.timeoutFirstCaptures);
    if (s.disconnectAfterFrames >= 0) (*faulty)->disconnectAfter(s.disconnectAfterFrames);
    return std::unique_ptr<hw::Camera>(std::move(faulty).value());
}

} // namespace slicestation::daemon
