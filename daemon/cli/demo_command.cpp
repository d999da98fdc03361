#include "slicestation/daemon/cli/demo_command.hpp"

#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

core::Result<json> runDemo(const DemoRequest& rq) {
    std::error_code ec;
    std::filesystem::create_directories(rq.outputDir, ec);
    if (ec)
        return makeError(ErrorCode::IoError, "cannot create " + rq.outputDir.string(), ec.value());
    const cv::Mat atlas = sim::builtinAtlasPlane(0.5);
    sim::GeneratorOptions go;
    go.seed = rq.seed;
    go.damage.tear = rq.damaged;
    auto gen = sim::generateSection(atlas, go);
    if (!gen)
        return gen.error();

    const auto dir = rq.outputDir;
    if (auto w = core::writeImage(dir / "atlas-labels.tif", atlas); !w)
        return w.error();
    if (auto w = core::writeImage(dir / "section.tif", gen->image); !w)
        return w.error();
    std::ostringstream pts, truth;
    pts << "x,y\n";
    truth << "x,y,atlas_x,atlas_y\n";
    for (const auto& l : gen->truth.landmarks) {
        pts << l.image.x << ',' << l.image.y << '\n';
        truth << l.image.x << ',' << l.image.y << ',' << l.atlas.x << ',' << l.atlas.y << '\n';
    }
    if (auto w = core::writeFileAtomically(dir / "landmarks.csv", pts.str()); !w)
        return w.error();
    if (auto w = core::writeFileAtomically(dir / "truth.csv", truth.str()); !w)
        return w.error();

    RegisterRequest rr;
    rr.atlas = dir / "atlas-labels.tif";
    rr.image = dir / "section.tif";
    rr.points = dir / "landmarks.csv";
    rr.output = dir / "result.json";
    rr.overlay = dir / "overlay.png";
    auto result = runRegister(rr);
    if (!result)
        return result.error();

    std::vector<double> err;
    const auto& mapped = (*result)["points"];
    for (size_t i = 0; i < gen->truth.landmarks.size(); ++i) {
        const auto& l = gen->truth.landmarks[i];
        err.push_back(std::hypot(mapped[i]["atlas_x"].get<double>() - l.atlas.x,
                                 mapped[i]["atlas_y"].get<double>() - l.atlas.y));
    }
    double ss = 0;
    for (double e : err)
        ss += e * e;
    std::vector<double> sorted = err;
    std::sort(sorted.begin(), sorted.end());
    json summary;
    summary["output_dir"] = dir.string();
    summary["landmarks"] = err.size();
    summary["rmse_atlas_px"] = err.empty() ? 0.0 : std::sqrt(ss / double(err.size()));
    summary["median_error_atlas_px"] = sorted.empty() ? 0.0 : sorted[sorted.size() / 2];
    summary["max_error_atlas_px"] = sorted.empty() ? 0.0 : sorted.back();
    summary["damaged"] = (*result)["damaged"];
    summary["damage_summary"] = (*result)["damage_summary"];
    summary["quality"] = (*result)["quality"];
    summary["timings_ms"] = (*result)["timings_ms"];
    summary["files"] = {"section.tif", "atlas-labels.tif", "landmarks.csv",
                        "truth.csv",   "result.json",      "overlay.png"};
    return summary;
}

} // namespace slicestation::daemon
