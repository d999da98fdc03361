#include "slicestation/daemon/config/station_config.hpp"

#include "station_file.hpp"

#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <initializer_list>
#include <sstream>
#include <string_view>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

using namespace station_file;

/// [camera.sim]: the sections on the virtual slide, real images or generated sections (default:
/// four, front to back, one torn).
core::Result<void> readSimSlideContent(const Json& t, const Reader& rd, const std::string& p,
                                       SimCameraSection& c) {
    auto& sl = c.slide;
    if (t.contains("images")) {
        const Json* a = &t["images"];
        if (!a->is_array() || a->empty())
            return rd.bad(p + "images", "expected a non-empty array of file names");
        if (a->size() > kMaxSimSections)
            return rd.bad(p + "images", "at most " + std::to_string(kMaxSimSections) + " images");
        for (std::size_t i = 0; i < a->size(); ++i) {
            if (!(*a)[i].is_string())
                return rd.bad(p + "images[" + std::to_string(i) + "]", "expected a file name");
            std::filesystem::path f = (*a)[i].get<std::string>();
            if (f.is_relative())
                f = std::filesystem::path(rd.origin).parent_path() / f;
            c.images.push_back(f);
        }
        if (t.contains("sections"))
            return rd.bad(p + "sections", "give either images or sections, not both");
    } else if (t.contains("sections")) {
        const Json* a = &t["sections"];
        if (!a->is_array() || a->empty() ||
            !std::all_of(a->begin(), a->end(), [](const Json& e) { return e.is_object(); }))
            return rd.bad(p + "sections", "expected [[camera.sim.sections]] tables");
        if (a->size() > kMaxSimSections)
            return rd.bad(p + "sections",
                          "at most " + std::to_string(kMaxSimSections) + " sections");
        for (std::size_t i = 0; i < a->size(); ++i) {
            const Json& st = (*a)[i];
            const std::string sp = p + "sections[" + std::to_string(i) + "].";
            if (auto k = rd.keys(st, sp, {"ap_fraction", "damage", "seed"}); !k)
                return k.error();
            sim::SlideSectionSpec spec;
            auto ap = rd.number(st, sp, "ap_fraction", std::nullopt, 0);
            if (!ap)
                return ap.error();
            if (*ap > 1)
                return rd.bad(sp + "ap_fraction", "must be in [0, 1]");
            spec.apFraction = *ap;
            auto dmg = rd.string(st, sp, "damage", std::string());
            if (!dmg)
                return dmg.error();
            if (*dmg != "" && *dmg != "tear" && *dmg != "missing" && *dmg != "fragment")
                return rd.bad(sp + "damage",
                              "expected \"\", \"tear\", \"missing\" or \"fragment\", got \"" +
                                  *dmg + "\"");
            spec.damage = *dmg;
            auto seed = integer(rd, st, sp, "seed", static_cast<int>(i + 1), 0, 2'147'483'647);
            if (!seed)
                return seed.error();
            spec.seed = static_cast<std::uint64_t>(*seed);
            sl.sections.push_back(spec);
        }
    } else { // a default slide: four sections front to back, one torn
        sl.sections = {{0.2, "", 1}, {0.4, "tear", 2}, {0.6, "", 3}, {0.8, "missing", 4}};
    }
    return {};
}

/// The slide is one image in memory: bounded before it is allocated.
core::Result<void> checkSimSlideSize(const SimCameraSection& c, const Reader& rd,
                                     const std::string& p) {
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
                         {"sensor_um_per_px", "focus_z_um", "focus_tilt_x", "focus_tilt_y",
                          "blur_sigma_px_per_um", "slide_um_per_px", "slide_origin_x_um",
                          "slide_origin_y_um", "section_pitch_um", "section_width_um", "margin_um",
                          "images_um_per_px", "columns", "brightfield", "timeout_first_captures",
                          "disconnect_after_frames", "images", "sections"});
        !k)
        return k.error();
    struct Num {
        const char* key;
        double* target;
        double min;
        double max;
    };
    auto& sl = c.slide;
    for (const Num& n :
         {Num{"sensor_um_per_px", &c.sensorUmPerPx, 1e-3, 1e4},
          Num{"focus_z_um", &c.focusZUm, -1e6, 1e6}, Num{"focus_tilt_x", &c.focusTiltX, -10, 10},
          Num{"focus_tilt_y", &c.focusTiltY, -10, 10},
          Num{"blur_sigma_px_per_um", &c.blurSigmaPxPerUm, 0, 100},
          Num{"slide_um_per_px", &sl.umPerPx, 0.1, 1e4},
          Num{"slide_origin_x_um", &sl.originXUm, -1e7, 1e7},
          Num{"slide_origin_y_um", &sl.originYUm, -1e7, 1e7},
          Num{"section_pitch_um", &sl.sectionPitchUm, 1e-3, 1e6},
          Num{"section_width_um", &sl.sectionWidthUm, 1e-3, 1e6},
          Num{"margin_um", &sl.marginUm, 0, 1e6},
          Num{"images_um_per_px", &c.imagesUmPerPx, 0.1, 1e4}}) {
        auto v = rd.number(t, p, n.key, *n.target, n.min, n.max);
        if (!v)
            return v.error();
        *n.target = *v;
    }
    if (sl.sectionWidthUm > sl.sectionPitchUm)
        return rd.bad(p + "section_width_um", "must not exceed section_pitch_um");
    auto cols = integer(rd, t, p, "columns", sl.columns, 1, 1000);
    if (!cols)
        return cols.error();
    sl.columns = *cols;
    auto bf = boolean(t, "brightfield", false, rd);
    if (!bf)
        return rd.bad(p + "brightfield", "expected true or false");
    sl.brightfield = *bf;
    auto to = integer(rd, t, p, "timeout_first_captures", 0, 0, 1'000'000);
    if (!to)
        return to.error();
    c.timeoutFirstCaptures = *to;
    auto dc = integer(rd, t, p, "disconnect_after_frames", -1, -1, 1'000'000'000);
    if (!dc)
        return dc.error();
    c.disconnectAfterFrames = *dc;

    if (auto r = readSimSlideContent(t, rd, p, c); !r)
        return r.error();
    if (auto r = checkSimSlideSize(c, rd, p); !r)
        return r.error();
    return c;
}

core::Result<CameraConfig> parseCamera(const Json& t, const Reader& rd) {
    CameraConfig c;
    const std::string p = "camera.";
    auto driver = rd.string(t, p, "driver", std::nullopt);
    if (!driver)
        return driver.error();
    c.driver = *driver;
    if (c.driver != "v4l2" && c.driver != "libcamera" && c.driver != "sim")
        return rd.bad("camera.driver",
                      "expected \"v4l2\", \"libcamera\" or \"sim\", got \"" + c.driver + "\"");
    {
        const std::initializer_list<std::string_view> known = {
            "driver",   "device",    "camera_id",         "format",
            "width",    "height",    "exposure_us",       "gain",
            "red_gain", "blue_gain", "capture_timeout_s", "settle_frames",
            "sim"};
        // A key of another driver is refused as such, not ignored.
        for (const auto& [key, owner] :
             {std::pair{"device", "v4l2"}, std::pair{"camera_id", "libcamera"},
              std::pair{"sim", "sim"}})
            if (t.contains(key) && c.driver != owner)
                return rd.bad(p + key, std::string("only for driver = \"") + owner + "\"");
        if (auto k = rd.keys(t, p, known); !k)
            return k.error();
    }
    auto device = rd.string(t, p, "device", c.device);
    if (!device)
        return device.error();
    c.device = *device;
    auto id = rd.string(t, p, "camera_id", std::string());
    if (!id)
        return id.error();
    c.cameraId = *id;
    auto fmt = rd.string(t, p, "format", std::string("mono8"));
    if (!fmt)
        return fmt.error();
    if (*fmt == "mono8")
        c.settings.format = hw::PixelFormat::Mono8;
    else if (*fmt == "mono16")
        c.settings.format = hw::PixelFormat::Mono16;
    else if (*fmt == "rgb8")
        c.settings.format = hw::PixelFormat::Rgb8;
    else
        return rd.bad("camera.format",
                      "expected \"mono8\", \"mono16\" or \"rgb8\", got \"" + *fmt + "\"");
    auto w = integer(rd, t, p, "width", 1024, 16, 16384);
    if (!w)
        return w.error();
    auto h = integer(rd, t, p, "height", 768, 16, 16384);
    if (!h)
        return h.error();
    c.settings.width = *w;
    c.settings.height = *h;
    auto exp = rd.number(t, p, "exposure_us", 10'000.0, 1);
    if (!exp)
        return exp.error();
    if (*exp > 10'000'000)
        return rd.bad("camera.exposure_us", "must be 1..10000000");
    c.settings.exposureUs = std::llround(*exp);
    auto gain = rd.number(t, p, "gain", 1.0, 1e-6, 1000);
    if (!gain)
        return gain.error();
    c.settings.analogueGain = *gain;
    auto rg = rd.number(t, p, "red_gain", 1.0, 1e-6, 100);
    if (!rg)
        return rg.error();
    auto bg = rd.number(t, p, "blue_gain", 1.0, 1e-6, 100);
    if (!bg)
        return bg.error();
    c.settings.redGain = *rg;
    c.settings.blueGain = *bg;
    auto ct = rd.number(t, p, "capture_timeout_s", 5.0, 0.001, 600);
    if (!ct)
        return ct.error();
    c.captureTimeout = std::chrono::milliseconds(std::llround(*ct * 1000));
    auto settle = integer(rd, t, p, "settle_frames", 3, 0, 100);
    if (!settle)
        return settle.error();
    c.settleFrames = *settle;
    if (c.driver == "sim") {
        static const Json empty = Json::object();
        if (t.contains("sim") && !t["sim"].is_object())
            return rd.bad("camera.sim", "expected a table");
        const Json* st = table(t, "sim");
        auto s = parseSimCamera(st ? *st : empty, rd);
        if (!s)
            return s.error();
        c.sim = std::move(*s);
    }
    return c;
}

} // namespace

namespace {

core::Result<StationConfig> stationFromDocument(const Json& root,
                                                const std::filesystem::path& origin) {
    Reader rd{origin.string()};
    if (auto k = rd.fields.onlyKeys(root, "(document)", kStationTables); !k)
        return k.error();
    StationConfig cfg;
    cfg.file = origin;
    const Json* st = table(root, "stage");
    if (!st)
        return rd.bad("stage", "missing table [stage]");
    auto stage = parseStage(*st, rd);
    if (!stage)
        return stage.error();
    cfg.stage = std::move(*stage);
    if (root.contains("camera")) {
        if (!root["camera"].is_object())
            return rd.bad("camera", "expected a table [camera]");
        auto c = parseCamera(root["camera"], rd);
        if (!c)
            return c.error();
        cfg.camera = std::move(*c);
    }
    return cfg;
}

} // namespace

core::Result<StationConfig> parseStationConfig(std::string_view text,
                                               const std::filesystem::path& origin) {
    auto doc = parseDocument(text, DocumentFormat::Toml, origin.string());
    if (!doc)
        return doc.error();
    return stationFromDocument(*doc, origin);
}

core::Result<StationConfig> loadStationConfig(const std::filesystem::path& file) {
    std::error_code ec;
    if (!std::filesystem::exists(file, ec))
        return makeError(ErrorCode::NotFound,
                         "station file " + file.string() + " cannot be opened");
    auto doc = readDocument(file); // bounded in size, like every document
    if (!doc)
        return doc.error();
    return stationFromDocument(*doc, file);
}

} // namespace slicestation::daemon
