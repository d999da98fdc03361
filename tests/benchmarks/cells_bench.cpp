// Cells per region (issue 22): generated sections of both families with labelled cells at known
// positions, registered to their atlas plane (the registration in the loop), cells detected and
// counted per region (pipeline/cells.hpp). Prints per-region count errors against the truth
// (rolled up the ontology like the measured counts), the detector's precision and recall on
// cell positions, and the same counts through the TRUE map (detector error alone).
// The detector's parameters were chosen on family 1; family 2 is the report.
#include "bench_cases.hpp"

#include "slicestation/pipeline/cells.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <CLI/CLI.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <string>
#include <vector>

using namespace slicestation;
using Clock = std::chrono::steady_clock;

namespace {

struct Match {
    int truePositives = 0, detected = 0, truth = 0;
};

/// Greedy one-to-one matching of detections to visible true cells within `radius`, closest
/// pairs first. A Threshold cluster of k cells counts as k detections at its centroid.
Match matchCells(const std::vector<pipeline::DetectedCell>& found,
                 const std::vector<sim::TrueCell>& truth, double radius) {
    Match m;
    std::vector<cv::Point2d> det;
    std::vector<double> reach; // a cluster's copies sit on one point: twice the radius
    for (const auto& d : found)
        for (int k = 0; k < d.clusterCells; ++k) {
            det.push_back(d.imagePx);
            reach.push_back(d.clusterCells > 1 ? 2 * radius : radius);
        }
    std::vector<cv::Point2d> tru;
    for (const auto& t : truth)
        if (t.counted)
            tru.push_back(t.image);
    m.detected = int(det.size());
    m.truth = int(tru.size());
    // Buckets keep this linear for thousands of cells.
    const double b = radius;
    std::map<std::pair<int, int>, std::vector<int>> grid;
    for (size_t i = 0; i < tru.size(); ++i)
        grid[{int(std::floor(tru[i].x / b)), int(std::floor(tru[i].y / b))}].push_back(int(i));
    struct Pair {
        double d;
        int det, tru;
    };
    std::vector<Pair> pairs;
    for (size_t i = 0; i < det.size(); ++i) {
        const int gx = int(std::floor(det[i].x / b)), gy = int(std::floor(det[i].y / b));
        for (int dx = -2; dx <= 2; ++dx)
            for (int dy = -2; dy <= 2; ++dy) {
                auto it = grid.find({gx + dx, gy + dy});
                if (it == grid.end())
                    continue;
                for (int j : it->second) {
                    const double d = cv::norm(det[i] - tru[size_t(j)]);
                    if (d <= reach[i])
                        pairs.push_back({d, int(i), j});
                }
            }
    }
    std::sort(pairs.begin(), pairs.end(), [](const Pair& x, const Pair& y) { return x.d < y.d; });
    std::vector<char> usedD(det.size(), 0), usedT(tru.size(), 0);
    for (const Pair& p : pairs) {
        if (usedD[size_t(p.det)] || usedT[size_t(p.tru)])
            continue;
        usedD[size_t(p.det)] = usedT[size_t(p.tru)] = 1;
        ++m.truePositives;
    }
    return m;
}

struct RegionError {
    std::string family, method;
    int caseIndex = 0;
    bool damaged = false, brightfield = false;
    bool nissl = false; ///< family 2's Nissl stain (every cell body stained, dense, touching)
    std::uint32_t id = 0;
    std::int64_t truth = 0, measured = 0, viaTrueMap = 0;
};

std::map<std::uint32_t, std::int64_t> truthCounts(const std::vector<sim::TrueCell>& cells,
                                                  const core::Ontology& onto) {
    std::vector<pipeline::RegionCount> leaves;
    std::map<std::uint32_t, std::int64_t> perId;
    for (const auto& c : cells)
        if (c.counted && c.atlasId > 0)
            ++perId[std::uint32_t(c.atlasId)];
    for (const auto& [id, n] : perId) {
        pipeline::RegionCount r;
        r.id = id;
        r.cells = n;
        leaves.push_back(r);
    }
    std::map<std::uint32_t, std::int64_t> out;
    for (const auto& r : pipeline::rollUp(leaves, onto))
        out[r.id] = r.cells;
    return out;
}

/// Counts through the true map: each detection's label from truth.labelsInImage, the true
/// damage excluded; rolled up like the measured table.
std::map<std::uint32_t, std::int64_t> trueMapCounts(const std::vector<pipeline::DetectedCell>& d,
                                                    const sim::GroundTruth& truth,
                                                    const core::Ontology& onto) {
    std::vector<sim::TrueCell> asTruth;
    for (const auto& c : d) {
        const int x = int(std::lround(c.imagePx.x)), y = int(std::lround(c.imagePx.y));
        if (x < 0 || y < 0 || x >= truth.labelsInImage.cols || y >= truth.labelsInImage.rows)
            continue;
        sim::TrueCell t;
        t.image = c.imagePx;
        t.atlasId = truth.labelsInImage.at<std::int32_t>(y, x);
        t.counted = truth.damageMask.at<std::uint8_t>(y, x) == 0;
        for (int k = 0; k < c.clusterCells; ++k)
            asTruth.push_back(t);
    }
    return truthCounts(asTruth, onto);
}

double percentile(std::vector<double> v, double q) {
    if (v.empty())
        return 0;
    std::sort(v.begin(), v.end());
    return v[std::min(v.size() - 1, size_t(q * double(v.size())))];
}

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"Cells per region benchmark (issue 22)"};
    std::string family = "all", size = "1500x1100", shared = SLST_SHARED_DIR, methods = "both";
    int cases = 8, firstCase = 0, minCells = 100;
    double diameter = 6, density = 1500, contrast = 2.0, minSnr = 4, minSep = 0.6, splitAt = 1.5;
    bool verbose = false;
    std::string dump;
    app.add_option("--family", family, "1, 2 or all")->check(CLI::IsMember({"1", "2", "all"}));
    app.add_option("--cases", cases, "Sections per family")->check(CLI::Range(1, 200));
    app.add_option(
           "--first-case", firstCase,
           "Skip the cases before this one (e.g. a held-out half: --first-case 24 --cases 48)")
        ->check(CLI::Range(0, 199));
    app.add_option("--size", size, "Section image size WxH");
    app.add_option("--shared", shared, "Shared data directory");
    app.add_option("--diameter", diameter, "Cell diameter, px (generator and detector)");
    app.add_option("--density", density, "Mean cells per 10^6 tissue px");
    app.add_option("--contrast", contrast, "Cell contrast (generator)");
    app.add_option("--min-snr", minSnr, "Detector threshold, robust noise units");
    app.add_option("--min-separation", minSep, "Detector NMS radius, x diameter");
    app.add_option("--split-at", splitAt, "Detector: blob area / cell area splitting (0 = off)");
    app.add_option("--min-cells", minCells, "Regions with fewer true cells are not scored");
    app.add_option("--methods", methods, "log, threshold or both")
        ->check(CLI::IsMember({"log", "threshold", "both"}));
    app.add_flag("--verbose", verbose, "Print every scored region");
    app.add_option("--dump", dump,
                   "Write each case's image with true (green) and found (red) cells here");
    CLI11_PARSE(app, argc, argv);
    int w = 0, h = 0;
    if (std::sscanf(size.c_str(), "%dx%d", &w, &h) != 2) {
        std::fprintf(stderr, "--size must be WxH\n");
        return 1;
    }
    auto atlas = bench::loadAtlasPlanes(shared, 12);
    if (!atlas) {
        std::fprintf(stderr, "atlas: %s\n", atlas.error().message.c_str());
        return 1;
    }
    std::vector<bench::BenchCase> all;
    if (family != "2")
        for (auto& c : bench::makeCases(cases, int(atlas->planes.size()), {w, h}))
            if (c.index >= firstCase)
                all.push_back(c);
    if (family != "1")
        for (auto& c : bench::makeCasesB(cases, int(atlas->planes.size()), {w, h}))
            if (c.index >= firstCase)
                all.push_back(c);
    std::vector<pipeline::CellMethod> ms;
    if (methods != "threshold")
        ms.push_back(pipeline::CellMethod::LoG);
    if (methods != "log")
        ms.push_back(pipeline::CellMethod::Threshold);

    sim::CellOptions cellOpt;
    cellOpt.enabled = true;
    cellOpt.diameterPx = diameter;
    cellOpt.meanPerMpx = density;
    cellOpt.contrast = contrast;

    std::printf("atlas %s; %s; cells %.1f px, %.0f per Mpx, contrast %.2f; detector min-snr %.1f "
                "min-separation %.2f split-at %.2f\n",
                atlas->name.c_str(), size.c_str(), diameter, density, contrast, minSnr, minSep,
                splitAt);
    std::printf("%-6s %-4s %-9s %-28s %6s %6s %6s %7s %7s %7s %8s %8s\n", "family", "case",
                "method", "section", "true", "found", "TP", "prec", "recall", "regions", "err_med%",
                "err_max%");
    std::vector<RegionError> errors;
    std::map<std::string, Match> totals;
    std::map<std::string, double> detectMs;
    for (const auto& c : all) {
        const bool first = c.family == bench::Family::First;
        const std::string fam = first ? "1" : "2";
        std::vector<sim::TrueCell> trueCells;
        cv::Mat image;
        sim::GroundTruth truth;
        if (first) {
            sim::GeneratorOptions o = c.options;
            o.cells = cellOpt;
            auto g = sim::generateSection(atlas->planes[size_t(c.plane)], o);
            if (!g) {
                std::fprintf(stderr, "generate: %s\n", g.error().message.c_str());
                return 1;
            }
            image = g->image;
            truth = std::move(g->truth);
            trueCells = std::move(g->cells);
        } else {
            sim::GeneratorOptionsB o = c.optionsB;
            o.atlasUmPerPx = atlas->umPerPx;
            o.cells = cellOpt;
            auto g = sim::generateSectionB(atlas->fullPlanes[size_t(c.plane)], atlas->ontology, o);
            if (!g) {
                std::fprintf(stderr, "generate: %s\n", g.error().message.c_str());
                return 1;
            }
            image = g->image;
            truth = std::move(g->truth);
            trueCells = std::move(g->cells);
        }
        // Family 1 renders the collapsed plane (major-region ids), family 2 every Allen id: the
        // truth is rolled up the ontology either way, so both compare at the registered
        // (collapsed) plane's regions and their ancestors.
        const auto truthTable = truthCounts(trueCells, atlas->ontology);
        const cv::Mat& plane = atlas->planes[size_t(c.plane)];
        auto reg = pipeline::registerSection(image, plane, {});
        if (!reg) {
            std::fprintf(stderr, "%s: registration failed: %s\n", c.describe().c_str(),
                         reg.error().message.c_str());
            continue;
        }
        cv::Mat tissue;
        cv::resize(reg->workingTissueMask, tissue, image.size(), 0, 0, cv::INTER_NEAREST);
        for (const auto m : ms) {
            pipeline::CellDetectorOptions d;
            d.diameterPx = diameter;
            d.minSnr = minSnr;
            d.minSeparation = minSep;
            d.splitAt = splitAt;
            d.method = m;
            d.mask = tissue;
            // Brightfield: the blue channel, where the brown label absorbs most (as a user picks
            // the channel of the label with --channel).
            d.channel = image.channels() == 3 ? 2 : -1;
            const auto t0 = Clock::now();
            auto found = pipeline::detectCells(image, d);
            const std::string method(pipeline::toString(m));
            detectMs[fam + " " + method] +=
                std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
            if (!found) {
                std::fprintf(stderr, "detect: %s\n", found.error().message.c_str());
                return 1;
            }
            auto table = pipeline::countCells(*reg, plane, *found, atlas->ontology);
            if (!table) {
                std::fprintf(stderr, "count: %s\n", table.error().message.c_str());
                return 1;
            }
            if (!dump.empty()) {
                cv::Mat view;
                cv::Mat grey = image;
                if (grey.channels() == 3)
                    cv::cvtColor(grey, grey, cv::COLOR_BGR2GRAY);
                cv::normalize(grey, view, 0, 255, cv::NORM_MINMAX, CV_8U);
                cv::cvtColor(view, view, cv::COLOR_GRAY2BGR);
                for (const auto& t : trueCells)
                    cv::circle(view, t.image, int(diameter), {0, 255, 0}, 1);
                for (const auto& f : *found)
                    cv::drawMarker(view, f.imagePx, {0, 0, 255}, cv::MARKER_CROSS, int(diameter),
                                   1);
                cv::imwrite(dump + "/cells-" + fam + "-" + std::to_string(c.index) + "-" + method +
                                ".png",
                            view);
                const cv::Rect centre(w / 2 - 200, h / 2 - 150, 400, 300);
                cv::Mat zoom;
                cv::resize(view(centre), zoom, {}, 2, 2, cv::INTER_NEAREST);
                cv::imwrite(dump + "/zoom-" + fam + "-" + std::to_string(c.index) + "-" + method +
                                ".png",
                            zoom);
            }
            const auto viaTrue = trueMapCounts(*found, truth, atlas->ontology);
            const Match match = matchCells(*found, trueCells, 0.6 * diameter);
            const bool nissl = !first && c.optionsB.stain == sim::StainB::Nissl;
            for (const std::string& key :
                 {fam + " " + method, fam + " " + method + (nissl ? " nissl" : " other")}) {
                Match& tot = totals[key];
                tot.truePositives += match.truePositives;
                tot.detected += match.detected;
                tot.truth += match.truth;
            }
            std::vector<double> rel;
            for (const auto& r : table->regions) {
                auto t = truthTable.find(r.id);
                if (t == truthTable.end() || t->second < minCells)
                    continue;
                RegionError e{fam,   method, c.index,   c.damaged(), c.brightfield(),
                              nissl, r.id,   t->second, r.cells,     0};
                auto v = viaTrue.find(r.id);
                e.viaTrueMap = v == viaTrue.end() ? 0 : v->second;
                rel.push_back(100.0 * std::abs(double(e.measured - e.truth)) / double(e.truth));
                errors.push_back(e);
                if (verbose) {
                    const core::Structure* s = atlas->ontology.find(r.id);
                    std::printf("    %-8s true %6lld measured %6lld (%+6.1f%%) true map %6lld "
                                "(%+6.1f%%)\n",
                                s ? s->acronym.c_str() : "?", (long long)e.truth,
                                (long long)e.measured,
                                100.0 * double(e.measured - e.truth) / double(e.truth),
                                (long long)e.viaTrueMap,
                                100.0 * double(e.viaTrueMap - e.truth) / double(e.truth));
                }
            }
            std::printf("%-6s %-4d %-9s %-28s %6d %6d %6d %7.3f %7.3f %7zu %8.1f %8.1f\n",
                        fam.c_str(), c.index, method.c_str(), c.describe().substr(0, 28).c_str(),
                        match.truth, match.detected, match.truePositives,
                        match.detected ? double(match.truePositives) / match.detected : 0.0,
                        match.truth ? double(match.truePositives) / match.truth : 0.0, rel.size(),
                        percentile(rel, 0.5), rel.empty() ? 0.0 : percentile(rel, 1.0));
            std::fflush(stdout);
        }
    }

    std::printf("\nSummary: regions with >= %d true cells; error = |measured - true| / true\n",
                minCells);
    std::printf("%-6s %-9s %-8s %8s %8s %8s %8s %9s %8s %8s %8s %9s\n", "family", "method",
                "subset", "regions", "med%", "p90%", "max%", "<=5%", "trueMap", "precision",
                "recall", "ms/sect");
    for (const std::string fam : {"1", "2"})
        for (const auto m : ms) {
            const std::string method(pipeline::toString(m));
            for (const std::string subset : {"all", "clean", "damaged", "nissl", "other"}) {
                // Family 2 only: its Nissl sections and the sections of its other stains.
                if (fam == "1" && (subset == "nissl" || subset == "other"))
                    continue;
                std::vector<double> rel, relTrue;
                int within = 0, sections = 0;
                for (const auto& e : errors) {
                    if (e.family != fam || e.method != method)
                        continue;
                    if ((subset == "clean" && e.damaged) || (subset == "damaged" && !e.damaged) ||
                        (subset == "nissl" && !e.nissl) || (subset == "other" && e.nissl))
                        continue;
                    const double r =
                        100.0 * std::abs(double(e.measured - e.truth)) / double(e.truth);
                    rel.push_back(r);
                    relTrue.push_back(100.0 * std::abs(double(e.viaTrueMap - e.truth)) /
                                      double(e.truth));
                    within += r <= 5.0;
                }
                for (const auto& c : all)
                    sections += (c.family == bench::Family::First) == (fam == "1");
                if (rel.empty())
                    continue;
                // Precision and recall: of the subset's sections for the stain subsets, of all
                // the family's sections otherwise.
                const Match& t =
                    totals[fam + " " + method +
                           (subset == "nissl" || subset == "other" ? " " + subset : "")];
                std::printf("%-6s %-9s %-8s %8zu %8.1f %8.1f %8.1f %8.0f%% %7.1f%% %8.3f %8.3f "
                            "%9.0f\n",
                            fam.c_str(), method.c_str(), subset.c_str(), rel.size(),
                            percentile(rel, 0.5), percentile(rel, 0.9), percentile(rel, 1.0),
                            100.0 * within / double(rel.size()), percentile(relTrue, 0.5),
                            t.detected ? double(t.truePositives) / t.detected : 0.0,
                            t.truth ? double(t.truePositives) / t.truth : 0.0,
                            sections ? detectMs[fam + " " + method] / sections : 0.0);
            }
        }
    std::printf("(trueMap: median error of the same detections counted through the true map "
                "and true damage: the detector's share of the error)\n");
    return 0;
}
