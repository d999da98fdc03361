// `slicectl atlas match-series`: the sections of one brain, in cutting order, matched live with
// the series model (pipeline/series_matching.hpp) against a stack, as the station would do
// section by section. Prints a table, a progress line on stderr, and writes the JSON.
#include "slicestation/core/atomic_file.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/daemon/storage/stack_volume.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/series_matching.hpp"

#include <nlohmann/json.hpp>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;
namespace fs = std::filesystem;

struct SeriesRequest {
    fs::path stack;
    std::vector<fs::path> images; ///< in cutting order
    double intervalUm = 0;        ///< the plan's interval between sections, 0 = unknown
    std::vector<double> umPerPx;  ///< none (unknown), one for all, or one per image
    fs::path output;              ///< JSON; empty = none
    bool quiet = false;
    bool tiltSearch = false; ///< the brain's tilt from planes cut from the stack's volume
    fs::path volume;         ///< label volume; empty = the manifest's source.volume
    fs::path ontology;       ///< empty = the manifest's source.ontology (major-region stacks)
};

/// searchSeriesTilt with planes cut as `atlas slice` cut the stack's (same axes, orientation,
/// pixel size and region set).
core::Result<json> searchTilt(const StackVolume& v, double workUm,
                              const std::vector<pipeline::SectionFeatures>& sections,
                              const pipeline::SeriesMatcher& matcher) {
    using Clock = std::chrono::steady_clock;
    const auto t0 = Clock::now();
    const pipeline::PlaneFeatures planes = [&](double pos, double lr, double dv) {
        return stackPlaneFeatures(v, pos, lr, dv, workUm);
    };
    auto e = pipeline::searchSeriesTilt(sections, matcher.matches(), matcher.fit(), planes);
    if (!e)
        return e.error();
    return json{{"tilt_lr_deg", e->tiltColumnsDeg},
                {"tilt_dv_deg", e->tiltRowsDeg},
                {"score", e->score},
                {"sections", e->sections},
                {"tilts", e->tiltsScored},
                {"volume", v.path.string()},
                {"ms", std::chrono::duration<double, std::milli>(Clock::now() - t0).count()}};
}

/// One section's entry of the JSON: `atlas match`'s fields plus its place in the series.
json sectionJson(const fs::path& image, const AtlasStack& stack, const pipeline::SectionMatch& m,
                 const pipeline::SeriesSectionFit& s, const pipeline::SeriesSearch& q) {
    json candidates = json::array();
    for (const auto& c : m.candidates)
        candidates.push_back({{"index", c.index},
                              {"position_um", stack.slices[size_t(c.index)].positionUm},
                              {"score", c.score},
                              {"overlap", c.overlap}});
    double ms = 0;
    for (const auto& [step, v] : m.timingsMs)
        ms += v;
    return {{"image", image.string()},
            {"index", m.index},
            {"position_um", m.positionUm},
            {"slice_position_um", stack.slices[size_t(m.index)].positionUm},
            {"score", m.score},
            {"tilt_lr_deg", m.tiltColumnsDeg},
            {"tilt_dv_deg", m.tiltRowsDeg},
            {"tilt_estimated", m.tiltEstimated},
            {"candidates", std::move(candidates)},
            {"timings_ms", {{"match", ms}, {"search", q.ms}}},
            {"series",
             {{"slot", s.slot},
              {"position_um", s.positionUm},
              {"line_position_um", s.predictedUm},
              {"residual_um", s.residualUm},
              {"on_line", s.inlier},
              {"anomaly", std::string(pipeline::toString(s.anomaly))},
              {"missing_before", s.missingBefore},
              {"predicted_um", q.predictedUm},
              {"searched", {q.first, q.last}},
              {"windowed", q.windowed},
              {"fell_back", q.fellBack}}}};
}

core::Result<json> runSeries(const SeriesRequest& rq) {
    using Clock = std::chrono::steady_clock;
    const auto t0 = Clock::now();
    if (rq.images.empty())
        return makeError(ErrorCode::InvalidArgument, "no section images given");
    if (!rq.umPerPx.empty() && rq.umPerPx.size() != 1 && rq.umPerPx.size() != rq.images.size())
        return makeError(ErrorCode::InvalidArgument,
                         "--image-um-per-px takes one value for all images or one per image (" +
                             std::to_string(rq.images.size()) + "), not " +
                             std::to_string(rq.umPerPx.size()));
    auto stack = readStack(rq.stack);
    if (!stack)
        return stack.error();
    auto features = stackFeatures(*stack);
    if (!features)
        return features.error();
    const double workUm = features->front().workUmPerPx;
    // Read before any section is matched, so that a wrong file is refused at once.
    std::optional<StackVolume> tiltSource;
    if (rq.tiltSearch) {
        auto t = readStackVolume(*stack, rq.volume, rq.ontology, false);
        if (!t)
            return makeError(t.error().code, "--tilt-search: " + t.error().message);
        tiltSource = std::move(*t);
    }
    pipeline::SeriesMatchOptions options;
    options.model.intervalUm = rq.intervalUm;
    pipeline::SeriesMatcher matcher(*features, options);
    std::vector<pipeline::SectionFeatures> sections;
    for (size_t i = 0; i < rq.images.size(); ++i) {
        const fs::path& path = rq.images[i];
        const double um = rq.umPerPx.empty()       ? 0.0
                          : rq.umPerPx.size() == 1 ? rq.umPerPx.front()
                                                   : rq.umPerPx[i];
        auto image = core::readImage(path);
        if (!image)
            return makeError(image.error().code, path.string() + ": " + image.error().message);
        auto sec = pipeline::sectionFeatures(*image, um, workUm);
        if (!sec)
            return makeError(sec.error().code, path.string() + ": " + sec.error().message);
        auto m = matcher.add(*sec);
        if (!m)
            return makeError(m.error().code, path.string() + ": " + m.error().message);
        sections.push_back(std::move(*sec));
        if (!rq.quiet) {
            const auto& f = matcher.fit();
            std::fprintf(stderr, "\rsection %zu/%zu: %.0f um, spacing so far %.0f um   ", i + 1,
                         rq.images.size(), m->positionUm, f.spacingUm);
            std::fflush(stderr);
        }
    }
    if (!rq.quiet)
        std::fprintf(stderr, "\n");
    if (auto r = matcher.finish(sections); !r)
        return r.error();
    const auto& fit = matcher.fit();
    json out;
    out["stack"] = stack->dir.string();
    json list = json::array();
    for (size_t i = 0; i < matcher.matches().size(); ++i)
        list.push_back(sectionJson(rq.images[i], *stack, matcher.matches()[i], fit.sections[i],
                                   matcher.searches()[i]));
    out["sections"] = std::move(list);
    out["series"] = {{"interval_um", rq.intervalUm},   {"spacing_um", fit.spacingUm},
                     {"origin_um", fit.originUm},      {"on_line", fit.inliers},
                     {"sigma_um", fit.sigmaUm},        {"tilt_lr_deg", fit.tiltColumnsDeg},
                     {"tilt_dv_deg", fit.tiltRowsDeg}, {"tilt_sections", fit.tiltSections}};
    if (tiltSource) {
        if (!rq.quiet)
            std::fprintf(stderr, "searching the tilt with planes cut from %s\n",
                         tiltSource->path.filename().string().c_str());
        auto t = searchTilt(*tiltSource, workUm, sections, matcher);
        if (!t)
            return t.error();
        out["series"]["tilt_search"] = std::move(*t);
    }
    out["timings_ms"] = {
        {"total", std::chrono::duration<double, std::milli>(Clock::now() - t0).count()}};
    if (!rq.output.empty())
        if (auto w = core::writeFileAtomically(rq.output, out.dump(2) + "\n"); !w)
            return w.error();
    return out;
}

} // namespace

CommandRunner addAtlasSeriesCommand(CLI::App& app) {
    CLI::App* atlas = app.get_subcommand("atlas");
    auto rq = std::make_shared<SeriesRequest>();
    auto* cmd = atlas->add_subcommand(
        "match-series",
        "Find the atlas plane of each section of one brain, given in cutting order, with the "
        "series model (position, spacing, tilt, skipped/swapped/out-of-order sections)");
    cmd->add_option("--stack", rq->stack, "Stack directory (or its manifest.json)")->required();
    cmd->add_option("--interval-um", rq->intervalUm,
                    "The cutting plan's interval between consecutive sections (0 = unknown)")
        ->check(finiteRange(0, 20000));
    cmd->add_option("--image-um-per-px", rq->umPerPx,
                    "Section pixel size: one value for all images or one per image")
        ->check(finiteRange(0.01, 1000));
    cmd->add_option("--output", rq->output, "Series JSON");
    cmd->add_flag("--quiet", rq->quiet, "No progress line on stderr");
    cmd->add_flag("--tilt-search", rq->tiltSearch,
                  "After the series, find the brain's cutting angle by matching the best sections "
                  "against tilted planes cut from the stack's volume (a few seconds)");
    cmd->add_option("--volume", rq->volume,
                    "Label volume for --tilt-search (default: the one the stack was cut from)");
    cmd->add_option("--ontology", rq->ontology,
                    "Ontology for --tilt-search on a major-region stack (default: the stack's)");
    cmd->add_option("images", rq->images, "Section images in cutting order")->required();
    return [=]() -> int {
        if (!*cmd)
            return -1;
        auto r = runSeries(*rq);
        if (!r)
            return reportError("atlas match-series", r.error());
        const json& out = *r;
        std::printf("%-28s %6s %9s %9s %9s %6s %6s %7s %7s  %s\n", "image", "slice", "pos_um",
                    "series_um", "line_um", "slot", "score", "tiltLR", "tiltDV", "anomaly");
        for (const auto& s : out["sections"]) {
            const std::string name = fs::path(s["image"].get<std::string>()).filename().string();
            std::printf("%-28s %6d %9.0f %9.0f %9.0f %6d %6.3f %7.1f %7.1f  %s\n", name.c_str(),
                        s["index"].get<int>(), s["position_um"].get<double>(),
                        s["series"]["position_um"].get<double>(),
                        s["series"]["line_position_um"].get<double>(),
                        s["series"]["slot"].get<int>(), s["score"].get<double>(),
                        s["tilt_lr_deg"].get<double>(), s["tilt_dv_deg"].get<double>(),
                        s["series"]["anomaly"].get<std::string>().c_str());
        }
        const json& f = out["series"];
        std::printf("series: spacing %.1f um, %d of %zu on the line (sigma %.0f um), tilt LR %.2f "
                    "DV %.2f deg from %d sections, %.1f s\n",
                    f["spacing_um"].get<double>(), f["on_line"].get<int>(), out["sections"].size(),
                    f["sigma_um"].get<double>(), f["tilt_lr_deg"].get<double>(),
                    f["tilt_dv_deg"].get<double>(), f["tilt_sections"].get<int>(),
                    out["timings_ms"]["total"].get<double>() / 1000);
        if (f.contains("tilt_search")) {
            const json& t = f["tilt_search"];
            std::printf("tilt from tilted planes: LR %.2f DV %.2f deg (%d sections, %d tilts, "
                        "%.1f s)\n",
                        t["tilt_lr_deg"].get<double>(), t["tilt_dv_deg"].get<double>(),
                        t["sections"].get<int>(), t["tilts"].get<int>(),
                        t["ms"].get<double>() / 1000);
        }
        return 0;
    };
}

} // namespace slicestation::daemon
