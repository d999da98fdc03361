// Registration benchmark: accuracy against ground truth and speed, ours and elastix side by side.
// Prints one table; per-case rows go to --csv when given.
#include "bench_cases.hpp"
#include "elastix_runner.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/damage.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "slicestation/pipeline/overlay.hpp"
#include "slicestation/pipeline/preprocess.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <CLI/CLI.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>

using namespace slicestation;

namespace {

/// Damage detection outcome of one case (ours only).
struct DamageRow {
    bool truth = false, flagged = false;
    /// The painted damage is large enough for the decision rule itself, measured on the true
    /// removed tissue (a painted tear can leave no more than a shallow notch).
    bool truthByRule = false;
    int trueRegions = 0, overlapped = 0;
    double ms = 0;
    std::string kinds;
};

struct Row {
    std::string method;
    bool damaged = false;
    bool failed = false; ///< the method returned no result at all
    bench::Errors err;
    double seconds = 0;
};

double median(std::vector<double> v) {
    if (v.empty()) return 0;
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
}

void printTable(const std::vector<Row>& rows) {
    std::printf("\n%-10s %-8s %5s %9s %10s %9s %9s %6s %9s\n", "method", "sections", "n",
                "avg RMSE", "avg median", "avg max", "worst max", "gross", "median s");
    std::map<std::pair<std::string, bool>, std::vector<const Row*>> groups;
    for (const auto& r : rows) groups[{r.method, r.damaged}].push_back(&r);
    for (const auto& [key, g] : groups) {
        double rmse = 0, med = 0, mx = 0, worst = 0;
        int gross = 0;
        std::vector<double> secs;
        for (const Row* r : g) {
            rmse += r->err.rmse;
            med += r->err.median;
            mx += r->err.max;
            worst = std::max(worst, r->err.max);
            if (r->failed || r->err.max > 25) ++gross;
            secs.push_back(r->seconds);
        }
        const double n = double(g.size());
        std::printf("%-10s %-8s %5zu %9.2f %10.2f %9.2f %9.2f %6d %9.3f\n", key.first.c_str(),
                    key.second ? "damaged" : "clean", g.size(), rmse / n, med / n, mx / n, worst,
                    gross, median(secs));
    }
    std::printf("(errors in atlas pixels; gross = max landmark error over 25 px or no result)\n");
}

/// Fills `polygon` (pixel coordinates, rounded) into `mask` with 255.
void fillPolygon(cv::Mat& mask, const std::vector<cv::Point2f>& polygon) {
    std::vector<cv::Point> rounded;
    for (const cv::Point2f& p : polygon) rounded.emplace_back(cvRound(p.x), cvRound(p.y));
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{rounded}, cv::Scalar(255));
}

/// The decision rule (pipeline::isDamaged, default parameters) applied to the true damage:
/// each removed region's share of the tissue, its length against the tissue's width and its
/// thickness (twice the largest inscribed radius).
bool damagedByRule(const sim::GroundTruth& truth) {
    const std::vector<cv::Point2f> all = pipeline::outerContourPoints(truth.tissueMask);
    if (all.empty()) return false;
    const cv::RotatedRect box = cv::minAreaRect(all);
    const double width = std::max(box.size.width, box.size.height);
    const double tissue = std::max(1, cv::countNonZero(truth.tissueMask));
    std::vector<pipeline::DamageRegion> regions;
    for (const auto& t : truth.damage) {
        if (t.polygon.size() < 3) continue;
        pipeline::DamageRegion r;
        r.kind = t.kind == sim::DamageKind::Tear      ? pipeline::DamageKind::Tear
                 : t.kind == sim::DamageKind::Missing ? pipeline::DamageKind::Missing
                                                      : pipeline::DamageKind::Fragment;
        r.areaPx = t.areaPx;
        r.share = t.areaPx / tissue;
        const cv::RotatedRect rb = cv::minAreaRect(t.polygon);
        r.lengthPx = std::max(rb.size.width, rb.size.height);
        cv::Mat region = cv::Mat::zeros(truth.tissueMask.size(), CV_8U), dist;
        fillPolygon(region, t.polygon);
        cv::distanceTransform(region, dist, cv::DIST_L2, 3);
        double radius = 0;
        cv::minMaxLoc(dist, nullptr, &radius);
        r.thicknessPx = 2 * radius;
        regions.push_back(r);
    }
    return pipeline::isDamaged(regions, width, pipeline::DamageParams{});
}

/// "precision P recall R (tp, fp, fn)" of the flags against the truth `truthOf` picks.
std::string flagScore(const std::vector<DamageRow>& d, bool DamageRow::*truthOf) {
    int tp = 0, fp = 0, fn = 0;
    for (const auto& r : d) {
        tp += r.*truthOf && r.flagged;
        fp += !(r.*truthOf) && r.flagged;
        fn += r.*truthOf && !r.flagged;
    }
    char buf[96];
    std::snprintf(buf, sizeof buf, "precision %.3f recall %.3f (tp %d, fp %d, fn %d)",
                  tp + fp ? double(tp) / (tp + fp) : 1.0, tp + fn ? double(tp) / (tp + fn) : 1.0,
                  tp, fp, fn);
    return buf;
}

void printDamage(const std::vector<DamageRow>& d, const std::vector<Row>& rows) {
    int regions = 0, overlapped = 0, below = 0;
    std::vector<double> ms;
    for (const auto& r : d) {
        regions += r.trueRegions;
        overlapped += r.overlapped;
        below += r.truth && !r.truthByRule;
        ms.push_back(r.ms);
    }
    double clean = 0, damaged = 0;
    int nc = 0, nd = 0;
    for (const auto& r : rows) {
        if (r.method != "ours") continue;
        (r.damaged ? damaged : clean) += r.err.rmse;
        ++(r.damaged ? nd : nc);
    }
    std::printf("\ndamage flag: %s\n", flagScore(d, &DamageRow::truth).c_str());
    std::printf("  against the painted damage the decision rule counts on the truth (%d damaged "
                "cases below it): %s\n",
                below, flagScore(d, &DamageRow::truthByRule).c_str());
    std::printf("true damage regions overlapped by a reported region: %d of %d (%.1f%%)\n",
                overlapped, regions, regions ? 100.0 * overlapped / regions : 100.0);
    if (nc && nd)
        std::printf("RMSE damaged / clean: %.2f\n", (damaged / nd) / std::max(clean / nc, 1e-9));
    std::printf("damage detection time: median %.1f ms, max %.1f ms per section\n", median(ms),
                ms.empty() ? 0.0 : *std::max_element(ms.begin(), ms.end()));
}

/// Which way round the Allen template's left-right axis runs relative to the QuickNII volume:
/// decided from the data by comparing the two annotation volumes, not assumed.
bool templateMirrored(const core::Volume& ann100, const cv::Mat& qnPlane25, int ap100) {
    auto p = pipeline::coronalPlane(ann100, pipeline::VolumeAxes::Allen, ap100);
    if (!p) return false;
    long same = 0, mirrored = 0;
    for (int r = 0; r < p->rows; ++r)
        for (int c = 0; c < p->cols; ++c) {
            const int rr = std::min(qnPlane25.rows - 1, r * 4 + 1);
            const int a = p->at<int>(r, c);
            if (a == 0) continue;
            if (a == qnPlane25.at<int>(rr, std::min(qnPlane25.cols - 1, c * 4 + 1))) ++same;
            if (a == qnPlane25.at<int>(rr, std::min(qnPlane25.cols - 1, (p->cols - 1 - c) * 4 + 1)))
                ++mirrored;
        }
    return mirrored > same;
}

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"slicestation registration benchmark"};
    std::string shared = SLST_SHARED_DIR, sizeText = "1500x1100", elastixMode = "auto", csvPath;
    std::string workDir = "/tmp/slst-bench";
    int cases = 48, elastixCases = -1;
    app.add_option("--shared", shared, "Path of ../shared (real atlas)");
    app.add_option("--cases", cases, "Number of generated sections")->check(CLI::Range(1, 1000));
    app.add_option("--size", sizeText, "Section image size WxH");
    app.add_option("--elastix", elastixMode, "auto | on | off")
        ->check(CLI::IsMember({"auto", "on", "off"}));
    app.add_option("--elastix-cases", elastixCases, "Run elastix on the first N cases (-1 = all)");
    app.add_option("--work", workDir, "Scratch directory for elastix");
    app.add_option("--csv", csvPath, "Write per-case rows here");
    std::vector<int> only;
    app.add_option("--only", only, "Run only these case indices of the --cases set (to look into them)");
    std::string overlayDir, refineMode = "on";
    app.add_option("--refine", refineMode, "Dense refinement of ours: on | off")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--overlays", overlayDir, "Write each case's overlay (ours, damage in red) here");
    CLI11_PARSE(app, argc, argv);
    int w = 0, h = 0;
    if (std::sscanf(sizeText.c_str(), "%dx%d", &w, &h) != 2 || w < 300 || h < 300) {
        std::cerr << "--size must be WxH with both at least 300\n";
        return 2;
    }

    auto atlas = bench::loadAtlasPlanes(shared, std::max(cases, 8));
    if (!atlas) {
        std::cerr << "cannot load the atlas: " << atlas.error().message << "\n";
        return 1;
    }
    bool useElastix = elastixMode == "on" || (elastixMode == "auto" && bench::elastixAvailable());
    if (elastixMode == "on" && !bench::elastixAvailable()) {
        std::cerr << "--elastix on, but elastix/transformix are not installed\n";
        return 1;
    }
    core::Volume templ, ann100;
    bool mirrored = false;
    if (useElastix) {
        const auto dir = std::filesystem::path(shared) / "atlas" / "allen-ccf-2017";
        auto t = core::readNrrd(dir / "average_template_100.nrrd");
        auto a = core::readNrrd(dir / "annotation_100.nrrd");
        if (!t || !a || atlas->name != "allen-ccf-25um") {
            std::cerr << "elastix needs the real atlas template; skipping elastix\n";
            useElastix = false;
        } else {
            templ = std::move(*t);
            ann100 = std::move(*a);
        }
    }
    std::printf("atlas: %s, %zu planes; %d cases of %dx%d px; elastix: %s\n", atlas->name.c_str(),
                atlas->planes.size(), cases, w, h, useElastix ? "yes" : "no");

    std::ofstream csv;
    if (!csvPath.empty()) {
        csv.open(csvPath);
        csv << "case,method,damaged,stain,rmse,median,max,seconds,failed\n";
    }
    std::vector<Row> rows;
    std::vector<DamageRow> damageRows;
    const auto all = bench::makeCases(cases, static_cast<int>(atlas->planes.size()), {w, h});
    for (const auto& c : all) {
        if (!only.empty() && std::find(only.begin(), only.end(), c.index) == only.end()) continue;
        const cv::Mat& plane = atlas->planes[c.plane];
        auto gen = sim::generateSection(plane, c.options);
        if (!gen) {
            std::cerr << c.describe() << ": generator failed: " << gen.error().message << "\n";
            return 1;
        }
        std::vector<cv::Point2d> pts;
        for (const auto& l : gen->truth.landmarks) pts.push_back(l.image);

        Row ours;
        ours.method = "ours";
        ours.damaged = c.damaged();
        const auto t0 = std::chrono::steady_clock::now();
        pipeline::RegistrationOptions ro;
        ro.denseRefine = refineMode == "on";
        auto reg = pipeline::registerSection(gen->image, plane, ro);
        ours.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (reg) {
            std::vector<cv::Point2d> mapped;
            for (const auto& p : pts) mapped.push_back(reg->atlasFromImage(p));
            ours.err = bench::landmarkErrors(gen->truth.landmarks, mapped);
        } else {
            ours.failed = true;
            std::cerr << c.describe() << ": ours failed: " << reg.error().message << "\n";
        }
        rows.push_back(ours);
        std::string steps;
        if (reg)
            for (const auto& [name, ms] : reg->timingsMs)
                steps += " " + name + " " + std::to_string(static_cast<int>(ms));
        if (reg) {
            // A true region counts as found when reported polygons cover a tenth of it.
            DamageRow d;
            d.truth = c.damaged();
            d.flagged = reg->damaged;
            for (const auto& [name, ms] : reg->timingsMs)
                if (name.rfind("damage", 0) == 0) d.ms += ms;
            cv::Mat reported = cv::Mat::zeros(gen->image.size(), CV_8U);
            for (const auto& r : reg->damage) {
                fillPolygon(reported, r.polygon);
                d.kinds += std::string(d.kinds.empty() ? "" : ",") +
                           std::string(pipeline::toString(r.kind));
            }
            d.truthByRule = d.truth && damagedByRule(gen->truth);
            for (const auto& t : gen->truth.damage) {
                cv::Mat truthMask = cv::Mat::zeros(gen->image.size(), CV_8U);
                fillPolygon(truthMask, t.polygon);
                const int area = std::max(1, cv::countNonZero(truthMask));
                ++d.trueRegions;
                if (cv::countNonZero(truthMask & reported) >= 0.1 * area) ++d.overlapped;
            }
            damageRows.push_back(d);
            if (!overlayDir.empty()) {
                const cv::Mat tile = pipeline::renderOverlay(*reg, plane);
                std::filesystem::create_directories(overlayDir);
                const auto path = std::filesystem::path(overlayDir) /
                                  ("case-" + std::to_string(c.index) + ".png");
                if (auto written = core::writeImage(path, tile); !written)
                    std::cerr << path << ": " << written.error().message << "\n";
            }
            char refined[64];
            std::snprintf(refined, sizeof refined, " | explained %.3f -> %.3f%s",
                          reg->quality.explainedBeforeRefine, reg->quality.explainedAfterRefine,
                          reg->quality.refined ? " kept" : "");
            steps += refined;
            steps += " | damage " + std::string(d.flagged ? "FLAGGED " : "clean ") + d.kinds;
        }
        std::fprintf(stderr, "%-45s ours    rmse %6.2f max %6.2f  %.3f s (ms:%s)\n",
                     c.describe().c_str(), ours.err.rmse, ours.err.max, ours.seconds,
                     steps.c_str());

        if (useElastix && (elastixCases < 0 || c.index < elastixCases)) {
            const int ap25 = atlas->apIndices[c.plane];
            const int ap100 = std::clamp(static_cast<int>(std::lround((ap25 + 0.5) / 4 - 0.5)), 0,
                                         templ.sizes[0] - 1);
            static const bool mirror = templateMirrored(ann100, plane, ap100);
            mirrored = mirror;
            cv::Mat moving(templ.sizes[1], templ.sizes[2], CV_32F);
            for (int r = 0; r < moving.rows; ++r)
                for (int col = 0; col < moving.cols; ++col)
                    moving.at<float>(r, col) = float(
                        templ.at(ap100, r, mirror ? moving.cols - 1 - col : col));
            bench::ElastixInput in;
            in.fixed = *pipeline::toGreyFloat(gen->image);
            // The calibration a user would enter: the true mean pixel size of this section.
            const auto& A = gen->truth.affineAtlasFromImage;
            in.fixedSpacingUm =
                atlas->umPerPx * std::sqrt(std::abs(A(0, 0) * A(1, 1) - A(0, 1) * A(1, 0)));
            in.moving = moving;
            in.movingSpacingUm = 100;
            in.movingOriginUm = 37.5; // centre of 100-um voxel 0 is 25-um pixel 1.5
            in.points = pts;
            const auto out = bench::runElastix(in, std::filesystem::path(workDir) /
                                                       ("case" + std::to_string(c.index)));
            Row el;
            el.method = "elastix";
            el.damaged = c.damaged();
            el.seconds = out.seconds;
            if (out.ok) {
                std::vector<cv::Point2d> mapped;
                for (const auto& m : out.mappedUm) mapped.push_back(m * (1.0 / atlas->umPerPx));
                el.err = bench::landmarkErrors(gen->truth.landmarks, mapped);
            } else {
                el.failed = true;
                std::cerr << c.describe() << ": elastix failed: " << out.error << "\n";
            }
            rows.push_back(el);
            std::fprintf(stderr, "%-45s elastix rmse %6.2f max %6.2f  %.3f s\n",
                         c.describe().c_str(), el.err.rmse, el.err.max, el.seconds);
        }
        if (csv) {
            for (auto it = rows.end() - (rows.back().method == "elastix" ? 2 : 1); it != rows.end(); ++it)
                csv << c.index << ',' << it->method << ',' << it->damaged << ','
                    << (c.options.stain == sim::Stain::Brightfield ? "brightfield" : "fluorescence")
                    << ',' << it->err.rmse << ',' << it->err.median << ',' << it->err.max << ','
                    << it->seconds << ',' << it->failed << '\n';
        }
    }
    if (useElastix) std::printf("template left-right mirrored against QuickNII: %s\n", mirrored ? "yes" : "no");
    printTable(rows);
    printDamage(damageRows, rows);
    return 0;
}
