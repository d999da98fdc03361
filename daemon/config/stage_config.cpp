// [stage] of the station file: driver, axes, motion, and the Modbus link.
#include "station_file.hpp"

#include <algorithm>
#include <cmath>

namespace slicestation::daemon::station_file {

namespace {

/// [stage]: the keys of its driver and transport only (a key of another names it).
core::Result<void> checkStageKeys(const Json& st, const Reader& rd, const std::string& driver) {
    const std::string p = "stage.";
    if (driver == "sim") {
        if (auto k =
                rd.keys(st, p,
                        {"driver", "move_timeout_s", "home_timeout_s", "axes", "speed_um_per_s",
                         "accel_um_per_s2", "position_window_um", "settle_ms"},
                        {"response_timeout_ms", "retries", "transport", "host", "port", "device",
                         "baud", "parity", "data_bits", "stop_bits", "map", "preset"},
                        "driver = \"modbus\"");
            !k)
            return k.error();
    } else {
        const bool tcp = st.contains("transport") && st["transport"] == "tcp";
        const std::initializer_list<std::string_view> common = {"driver",
                                                                "move_timeout_s",
                                                                "home_timeout_s",
                                                                "axes",
                                                                "speed_um_per_s",
                                                                "accel_um_per_s2",
                                                                "position_window_um",
                                                                "settle_ms",
                                                                "response_timeout_ms",
                                                                "retries",
                                                                "transport",
                                                                "map",
                                                                "preset",
                                                                "host",
                                                                "port",
                                                                "device",
                                                                "baud",
                                                                "parity",
                                                                "data_bits",
                                                                "stop_bits"};
        auto k =
            tcp ? rd.keys(st, p, common, {"device", "baud", "parity", "data_bits", "stop_bits"},
                          "transport = \"rtu\"")
                : rd.keys(st, p, common, {"host", "port"}, "transport = \"tcp\"");
        if (!k)
            return k.error();
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
    if (!axes)
        return rd.bad("stage.axes", "missing table (needs [stage.axes.x] and [stage.axes.y])");
    if (auto k = rd.keys(*axes, "stage.axes.", {"x", "y", "z"}); !k)
        return k.error();
    std::vector<drivers::ModbusAxisConfig> list;
    for (const char* name : {"x", "y", "z"}) {
        const Json* a = table(*axes, name);
        const std::string ap = "stage.axes." + std::string(name) + ".";
        if (!a) {
            if (std::string(name) == "z" && !axes->contains("z"))
                continue;
            return rd.bad("stage.axes." + std::string(name), "missing table");
        }
        if (auto k = driver == "modbus"
                         ? rd.keys(*a, ap, {"min_um", "max_um", "slave", "steps_per_um"})
                         : rd.keys(*a, ap, {"min_um", "max_um"}, {"slave", "steps_per_um"},
                                   "driver = \"modbus\"");
            !k)
            return k.error();
        drivers::ModbusAxisConfig ax;
        ax.name = name;
        auto mn = rd.number(*a, ap, "min_um", std::nullopt, -1e7, 1e7);
        if (!mn)
            return mn.error();
        auto mx = rd.number(*a, ap, "max_um", std::nullopt, -1e7, 1e7);
        if (!mx)
            return mx.error();
        if (!(*mn < *mx))
            return rd.bad(ap + "max_um", "must be greater than min_um");
        ax.minUm = *mn;
        ax.maxUm = *mx;
        if (driver == "modbus") {
            auto slave = rd.number(*a, ap, "slave", std::nullopt, 1, 247);
            if (!slave)
                return slave.error();
            if (*slave > 247 || std::floor(*slave) != *slave)
                return rd.bad(ap + "slave", "must be an integer 1..247");
            ax.slave = static_cast<int>(*slave);
            auto spu = rd.number(*a, ap, "steps_per_um", std::nullopt, 1e-9, 1e6);
            if (!spu)
                return spu.error();
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
    if (!transport)
        return transport.error();
    if (*transport == "tcp") {
        m.transport = drivers::ModbusStageConfig::Transport::Tcp;
        auto host = rd.string(st, p, "host", std::nullopt);
        if (!host)
            return host.error();
        m.host = *host;
        auto port = integer(rd, st, p, "port", 502, 1, 65535);
        if (!port)
            return port.error();
        m.port = *port;
    } else if (*transport == "rtu") {
        m.transport = drivers::ModbusStageConfig::Transport::Rtu;
        auto dev = rd.string(st, p, "device", std::nullopt);
        if (!dev)
            return dev.error();
        m.device = *dev;
        auto baud = integer(rd, st, p, "baud", 115200, 50, 4'000'000);
        if (!baud)
            return baud.error();
        m.baud = *baud;
        auto parity = rd.string(st, p, "parity", std::string("E"));
        if (!parity)
            return parity.error();
        if (*parity != "N" && *parity != "E" && *parity != "O")
            return rd.bad("stage.parity", "expected \"N\", \"E\" or \"O\"");
        m.parity = (*parity)[0];
        auto db = integer(rd, st, p, "data_bits", 8, 5, 8);
        if (!db)
            return db.error();
        m.dataBits = *db;
        auto sb = integer(rd, st, p, "stop_bits", 1, 1, 2);
        if (!sb)
            return sb.error();
        m.stopBits = *sb;
    } else {
        return rd.bad("stage.transport", "expected \"tcp\" or \"rtu\"");
    }

    if (st.contains("map")) {
        auto file = rd.string(st, p, "map", std::nullopt);
        if (!file)
            return file.error();
        std::filesystem::path f = *file;
        if (f.is_relative())
            f = std::filesystem::path(rd.origin).parent_path() / f;
        auto map = drivers::loadRegisterMap(f);
        if (!map)
            return makeError(map.error().code, rd.origin + ": stage.map: " + map.error().message);
        m.map = std::move(*map);
    } else {
        auto preset = rd.string(st, p, "preset", std::string("oriental-az"));
        if (!preset)
            return preset.error();
        auto map = drivers::presetMap(*preset);
        if (!map)
            return rd.bad("stage.preset", map.error().message);
        m.map = std::move(*map);
    }
    return {};
}

} // namespace

core::Result<StageConfig> parseStage(const Json& st, const Reader& rd) {
    StageConfig c;
    const std::string p = "stage.";
    auto driver = rd.string(st, p, "driver", std::nullopt);
    if (!driver)
        return driver.error();
    c.driver = *driver;
    if (c.driver != "modbus" && c.driver != "sim")
        return rd.bad("stage.driver", "expected \"modbus\" or \"sim\", got \"" + c.driver + "\"");
    if (auto k = checkStageKeys(st, rd, c.driver); !k)
        return k.error();
    auto ms = [](double s) { return std::chrono::milliseconds(std::llround(s * 1000)); };
    auto mt = rd.number(st, p, "move_timeout_s", 10.0, 0.001, 3600);
    if (!mt)
        return mt.error();
    c.moveTimeout = ms(*mt);
    auto ht = rd.number(st, p, "home_timeout_s", 60.0, 0.001, 3600);
    if (!ht)
        return ht.error();
    c.homeTimeout = ms(*ht);

    auto axes = readAxes(st, rd, c.driver);
    if (!axes)
        return axes.error();
    const std::vector<drivers::ModbusAxisConfig>& list = *axes;
    auto speed = rd.number(st, p, "speed_um_per_s", 10'000.0, 1e-6, 1e7);
    if (!speed)
        return speed.error();
    auto accel = rd.number(st, p, "accel_um_per_s2", 50'000.0, 1e-6, 1e9);
    if (!accel)
        return accel.error();
    auto window = rd.number(st, p, "position_window_um", 1.0, 1e-6, 1e5);
    if (!window)
        return window.error();
    auto settle = rd.number(st, p, "settle_ms", 50.0, 0, 60'000);
    if (!settle)
        return settle.error();

    if (c.driver == "sim") {
        c.sim.limits.x = {list[0].minUm, list[0].maxUm};
        c.sim.limits.y = {list[1].minUm, list[1].maxUm};
        c.sim.limits.z = list.size() > 2
                             ? std::optional<hw::AxisRange>({list[2].minUm, list[2].maxUm})
                             : std::nullopt;
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
    if (!rto)
        return rto.error();
    m.responseTimeout = std::chrono::milliseconds(std::llround(*rto));
    auto retries = integer(rd, st, p, "retries", 2, 0, 100);
    if (!retries)
        return retries.error();
    m.retries = *retries;

    if (auto l = readModbusLink(st, rd, m); !l)
        return l.error();
    return c;
}

} // namespace slicestation::daemon::station_file
