#include "slicestation/daemon/station_config.hpp"

#include "slicestation/drivers/libcamera_camera.hpp"
#include "slicestation/drivers/v4l2_camera.hpp"
#include "slicestation/sim/faulty_camera.hpp"

#include <toml++/toml.h>

#include <cmath>
#include <fstream>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

struct Reader {
    std::string origin;
    core::Error bad(const std::string& key, const std::string& what) const {
        return makeError(ErrorCode::InvalidArgument, origin + ": " + key + ": " + what);
    }
    core::Result<double> number(const toml::table& t, const std::string& prefix, const char* key,
                                std::optional<double> fallback, double min = -1e300) const {
        const toml::node* n = t.get(key);
        if (!n) {
            if (fallback) return *fallback;
            return bad(prefix + key, "missing");
        }
        const auto v = n->value<double>();
        if (!v || !std::isfinite(*v)) return bad(prefix + key, "expected a number");
        if (*v < min) return bad(prefix + key, "must be >= " + std::to_string(min));
        return *v;
    }
    core::Result<std::string> string(const toml::table& t, const std::string& prefix, const char* key,
                                     std::optional<std::string> fallback) const {
        const toml::node* n = t.get(key);
        if (!n) {
            if (fallback) return *fallback;
            return bad(prefix + key, "missing");
        }
        if (!n->is_string()) return bad(prefix + key, "expected a string");
        return n->as_string()->get();
    }
};

core::Result<StageConfig> parseStage(const toml::table& st, const Reader& rd) {
    StageConfig c;
    const std::string p = "stage.";
    auto driver = rd.string(st, p, "driver", std::nullopt);
    if (!driver) return driver.error();
    c.driver = *driver;
    if (c.driver != "modbus" && c.driver != "sim")
        return rd.bad("stage.driver", "expected \"modbus\" or \"sim\", got \"" + c.driver + "\"");
    auto ms = [](double s) { return std::chrono::milliseconds(std::llround(s * 1000)); };
    auto mt = rd.number(st, p, "move_timeout_s", 10.0, 0.001);
    if (!mt) return mt.error();
    c.moveTimeout = ms(*mt);
    auto ht = rd.number(st, p, "home_timeout_s", 60.0, 0.001);
    if (!ht) return ht.error();
    c.homeTimeout = ms(*ht);

    // Axes: [stage.axes.x], [stage.axes.y], optional [stage.axes.z].
    const toml::table* axes = st["axes"].as_table();
    if (!axes) return rd.bad("stage.axes", "missing table (needs [stage.axes.x] and [stage.axes.y])");
    std::vector<drivers::ModbusAxisConfig> list;
    for (const char* name : {"x", "y", "z"}) {
        const toml::table* a = (*axes)[name].as_table();
        const std::string ap = "stage.axes." + std::string(name) + ".";
        if (!a) {
            if (std::string(name) == "z") continue;
            return rd.bad("stage.axes." + std::string(name), "missing table");
        }
        drivers::ModbusAxisConfig ax;
        ax.name = name;
        auto mn = rd.number(*a, ap, "min_um", std::nullopt);
        if (!mn) return mn.error();
        auto mx = rd.number(*a, ap, "max_um", std::nullopt);
        if (!mx) return mx.error();
        if (!(*mn < *mx)) return rd.bad(ap + "max_um", "must be greater than min_um");
        ax.minUm = *mn;
        ax.maxUm = *mx;
        if (c.driver == "modbus") {
            auto slave = rd.number(*a, ap, "slave", std::nullopt, 1);
            if (!slave) return slave.error();
            if (*slave > 247 || std::floor(*slave) != *slave) return rd.bad(ap + "slave", "must be an integer 1..247");
            ax.slave = static_cast<int>(*slave);
            auto spu = rd.number(*a, ap, "steps_per_um", std::nullopt, 1e-9);
            if (!spu) return spu.error();
            ax.stepsPerUm = *spu;
        }
        list.push_back(ax);
    }
    auto speed = rd.number(st, p, "speed_um_per_s", 10'000.0, 1e-6);
    if (!speed) return speed.error();
    auto accel = rd.number(st, p, "accel_um_per_s2", 50'000.0, 1e-6);
    if (!accel) return accel.error();
    auto window = rd.number(st, p, "position_window_um", 1.0, 1e-6);
    if (!window) return window.error();
    auto settle = rd.number(st, p, "settle_ms", 50.0, 0);
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
    auto rto = rd.number(st, p, "response_timeout_ms", 200.0, 1);
    if (!rto) return rto.error();
    m.responseTimeout = std::chrono::milliseconds(std::llround(*rto));
    auto retries = rd.number(st, p, "retries", 2.0, 0);
    if (!retries) return retries.error();
    m.retries = static_cast<int>(*retries);

    auto transport = rd.string(st, p, "transport", std::nullopt);
    if (!transport) return transport.error();
    if (*transport == "tcp") {
        m.transport = drivers::ModbusStageConfig::Transport::Tcp;
        auto host = rd.string(st, p, "host", std::nullopt);
        if (!host) return host.error();
        m.host = *host;
        auto port = rd.number(st, p, "port", 502.0, 1);
        if (!port) return port.error();
        if (*port > 65535) return rd.bad("stage.port", "must be 1..65535");
        m.port = static_cast<int>(*port);
    } else if (*transport == "rtu") {
        m.transport = drivers::ModbusStageConfig::Transport::Rtu;
        auto dev = rd.string(st, p, "device", std::nullopt);
        if (!dev) return dev.error();
        m.device = *dev;
        auto baud = rd.number(st, p, "baud", 115200.0, 1);
        if (!baud) return baud.error();
        m.baud = static_cast<int>(*baud);
        auto parity = rd.string(st, p, "parity", std::string("E"));
        if (!parity) return parity.error();
        if (*parity != "N" && *parity != "E" && *parity != "O") return rd.bad("stage.parity", "expected \"N\", \"E\" or \"O\"");
        m.parity = (*parity)[0];
        auto db = rd.number(st, p, "data_bits", 8.0, 5);
        if (!db) return db.error();
        m.dataBits = static_cast<int>(*db);
        auto sb = rd.number(st, p, "stop_bits", 1.0, 1);
        if (!sb) return sb.error();
        m.stopBits = static_cast<int>(*sb);
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
    return c;
}

core::Result<bool> boolean(const toml::table& t, const std::string& key, bool fallback, const Reader& rd) {
    const toml::node* n = t.get(key);
    if (!n) return fallback;
    if (!n->is_boolean()) return rd.bad(key, "expected true or false");
    return n->as_boolean()->get();
}

core::Result<int> integer(const Reader& rd, const toml::table& t, const std::string& prefix, const char* key,
                          int fallback, int min, int max) {
    auto v = rd.number(t, prefix, key, double(fallback));
    if (!v) return v.error();
    if (std::floor(*v) != *v || *v < min || *v > max)
        return rd.bad(prefix + key, "must be an integer " + std::to_string(min) + ".." + std::to_string(max));
    return static_cast<int>(*v);
}

core::Result<SimCameraSection> parseSimCamera(const toml::table& t, const Reader& rd) {
    SimCameraSection c;
    const std::string p = "camera.sim.";
    struct Num {
        const char* key;
        double* target;
        double min;
    };
    auto& sl = c.slide;
    for (const Num& n : {Num{"sensor_um_per_px", &c.sensorUmPerPx, 1e-6}, Num{"focus_z_um", &c.focusZUm, -1e300},
                         Num{"focus_tilt_x", &c.focusTiltX, -1e300}, Num{"focus_tilt_y", &c.focusTiltY, -1e300},
                         Num{"blur_sigma_px_per_um", &c.blurSigmaPxPerUm, 0}, Num{"slide_um_per_px", &sl.umPerPx, 1e-6},
                         Num{"slide_origin_x_um", &sl.originXUm, -1e300}, Num{"slide_origin_y_um", &sl.originYUm, -1e300},
                         Num{"section_pitch_um", &sl.sectionPitchUm, 1e-6}, Num{"section_width_um", &sl.sectionWidthUm, 1e-6},
                         Num{"margin_um", &sl.marginUm, 0}, Num{"images_um_per_px", &c.imagesUmPerPx, 1e-6}}) {
        auto v = rd.number(t, p, n.key, *n.target, n.min);
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

    if (const toml::node* imgs = t.get("images")) {
        const toml::array* a = imgs->as_array();
        if (!a || a->empty()) return rd.bad(p + "images", "expected a non-empty array of file names");
        for (std::size_t i = 0; i < a->size(); ++i) {
            const auto v = (*a)[i].value<std::string>();
            if (!v) return rd.bad(p + "images[" + std::to_string(i) + "]", "expected a file name");
            std::filesystem::path f = *v;
            if (f.is_relative()) f = std::filesystem::path(rd.origin).parent_path() / f;
            c.images.push_back(f);
        }
        if (t.contains("sections")) return rd.bad(p + "sections", "give either images or sections, not both");
    } else if (const toml::node* secs = t.get("sections")) {
        const toml::array* a = secs->as_array();
        if (!a || a->empty() || !a->is_homogeneous(toml::node_type::table))
            return rd.bad(p + "sections", "expected [[camera.sim.sections]] tables");
        for (std::size_t i = 0; i < a->size(); ++i) {
            const toml::table& st = *(*a)[i].as_table();
            const std::string sp = p + "sections[" + std::to_string(i) + "].";
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
            auto seed = rd.number(st, sp, "seed", double(i + 1), 0);
            if (!seed) return seed.error();
            spec.seed = static_cast<std::uint64_t>(*seed);
            sl.sections.push_back(spec);
        }
    } else { // a default slide: four sections front to back, one torn
        sl.sections = {{0.2, "", 1}, {0.4, "tear", 2}, {0.6, "", 3}, {0.8, "missing", 4}};
    }
    return c;
}

core::Result<CameraConfig> parseCamera(const toml::table& t, const Reader& rd) {
    CameraConfig c;
    const std::string p = "camera.";
    auto driver = rd.string(t, p, "driver", std::nullopt);
    if (!driver) return driver.error();
    c.driver = *driver;
    if (c.driver != "v4l2" && c.driver != "libcamera" && c.driver != "sim")
        return rd.bad("camera.driver", "expected \"v4l2\", \"libcamera\" or \"sim\", got \"" + c.driver + "\"");
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
    auto gain = rd.number(t, p, "gain", 1.0, 1e-6);
    if (!gain) return gain.error();
    c.settings.analogueGain = *gain;
    auto rg = rd.number(t, p, "red_gain", 1.0, 1e-6);
    if (!rg) return rg.error();
    auto bg = rd.number(t, p, "blue_gain", 1.0, 1e-6);
    if (!bg) return bg.error();
    c.settings.redGain = *rg;
    c.settings.blueGain = *bg;
    auto ct = rd.number(t, p, "capture_timeout_s", 5.0, 0.001);
    if (!ct) return ct.error();
    c.captureTimeout = std::chrono::milliseconds(std::llround(*ct * 1000));
    auto settle = integer(rd, t, p, "settle_frames", 3, 0, 100);
    if (!settle) return settle.error();
    c.settleFrames = *settle;
    if (c.driver == "sim") {
        static const toml::table empty;
        const toml::table* st = t["sim"].as_table();
        auto s = parseSimCamera(st ? *st : empty, rd);
        if (!s) return s.error();
        c.sim = std::move(*s);
    } else if (t.contains("sim")) {
        return rd.bad("camera.sim", "only for driver = \"sim\"");
    }
    return c;
}

} // namespace

core::Result<StationConfig> parseStationConfig(std::string_view text, const std::filesystem::path& origin) {
    toml::table root;
    try {
        root = toml::parse(text, origin.string());
    } catch (const toml::parse_error& e) {
        std::ostringstream os;
        os << origin.string() << ":" << e.source().begin.line << ": " << e.description();
        return makeError(ErrorCode::InvalidArgument, os.str());
    }
    Reader rd{origin.string()};
    StationConfig cfg;
    cfg.file = origin;
    const toml::table* st = root["stage"].as_table();
    if (!st) return rd.bad("stage", "missing table [stage]");
    auto stage = parseStage(*st, rd);
    if (!stage) return stage.error();
    cfg.stage = std::move(*stage);
    if (const toml::node* cam = root.get("camera")) {
        if (!cam->is_table()) return rd.bad("camera", "expected a table [camera]");
        auto c = parseCamera(*cam->as_table(), rd);
        if (!c) return c.error();
        cfg.camera = std::move(*c);
    }
    return cfg;
}

core::Result<StationConfig> loadStationConfig(const std::filesystem::path& file) {
    std::ifstream in(file);
    if (!in) return makeError(ErrorCode::NotFound, "station file " + file.string() + " cannot be opened");
    std::stringstream ss;
    ss << in.rdbuf();
    return parseStationConfig(ss.str(), file);
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
