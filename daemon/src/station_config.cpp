#include "slicestation/daemon/station_config.hpp"

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
