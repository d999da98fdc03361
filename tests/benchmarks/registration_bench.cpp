// Registration benchmark: accuracy against ground truth and speed, ours and elastix side by side.
// Prints one table; per-case rows go to --csv when given.
#include "bench_cases.hpp"
#include "elastix_runner.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/damage.hpp"
#include "slicestation/pipeline/damage_series.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "slicestation/pipeline/overlay.hpp"
#include "slicestation/pipeline/preprocess.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <CLI/CLI.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>

using namespace slicestation;

namespace {

/// Damage detection outcome of one case (ours only).
struct DamageRow {
    bool truth = false, flagged = false;
    bool checkRegistration = false; ///< the verdict "check the registration" (not a flag)
    /// The painted damage is large enough for the decision rule itself, measured on the true
    /// removed tissue (a painted tear can leave no more than a shallow notch).
    bool truthByRule = false;
    int trueRegions = 0, overlapped = 0;
    double ms = 0;
    std::string kinds;
};

/// RMS of the vectors `v` at points `p` after removing their least-squares polynomial of
/// `degree` (1 or 3) in (x, y) (centred and scaled for the fit's conditioning; the residual does
/// not depend on it).
double polynomialResidualRms(const std::vector<cv::Point2d>& p, const std::vector<cv::Point2d>& v,
                             int degree) {
    CV_Assert(degree == 1 || degree == 3);
    cv::Point2d c(0, 0);
    for (const auto& q : p)
        c += q;
    c *= 1.0 / double(p.size());
    double scale = 1;
    for (const auto& q : p)
        scale = std::max(scale, cv::norm(q - c));
    const int terms = degree == 1 ? 3 : 10;
    cv::Mat A(int(p.size()), terms, CV_64F), bx(int(p.size()), 1, CV_64F),
        by(int(p.size()), 1, CV_64F);
    for (int i = 0; i < A.rows; ++i) {
        const double x = (p[size_t(i)].x - c.x) / scale, y = (p[size_t(i)].y - c.y) / scale;
        const double t[10] = {1,     x,         y,         x * x,     x * y,
                              y * y, x * x * x, x * x * y, x * y * y, y * y * y};
        for (int j = 0; j < terms; ++j)
            A.at<double>(i, j) = t[j];
        bx.at<double>(i) = v[size_t(i)].x;
        by.at<double>(i) = v[size_t(i)].y;
    }
    cv::Mat cx, cy;
    cv::solve(A, bx, cx, cv::DECOMP_SVD);
    cv::solve(A, by, cy, cv::DECOMP_SVD);
    const cv::Mat rx = A * cx - bx, ry = A * cy - by;
    return std::sqrt((rx.dot(rx) + ry.dot(ry)) / double(A.rows));
}

/// RMS distance (atlas px) of the true landmark positions from the best affine fit to them: how
/// much of the true map no affine can explain.
double nonAffineRms(const std::vector<sim::Landmark>& lms) {
    if (lms.size() < 3)
        return 0;
    std::vector<cv::Point2d> image, atlas;
    for (const auto& l : lms) {
        image.push_back(l.image);
        atlas.push_back(l.atlas);
    }
    return polynomialResidualRms(image, atlas, 1);
}

/// Where the error of one case lies (`--diagnose`): atlas px.
struct Diagnosis {
    double affine = 0; ///< RMSE of our affine alone
    double best = 0;  ///< RMSE of the best affine fit to the true landmarks (no affine does better)
    double local = 0; ///< RMSE of our final errors minus their best cubic polynomial in x, y
    double rim = 0;   ///< RMSE of our final errors within 3% of the tissue width of the outline
    double interior = 0; ///< RMSE of our final errors further inside
};

/// RMS of the error vectors `e` at image points `p` after removing their least-squares cubic
/// polynomial in (x, y): what a smooth field with about 4 x 4 degrees of freedom cannot fix.
double localPart(const std::vector<cv::Point2d>& p, const std::vector<cv::Point2d>& e) {
    return p.size() < 20 ? 0 : polynomialResidualRms(p, e, 3);
}

Diagnosis diagnose(const sim::GroundTruth& truth, const pipeline::Registration& reg) {
    Diagnosis d;
    d.best = nonAffineRms(truth.landmarks);
    cv::Mat dist;
    cv::distanceTransform(truth.tissueMask != 0, dist, cv::DIST_L2, 3);
    const std::vector<cv::Point2f> outline = pipeline::outerContourPoints(truth.tissueMask);
    const cv::RotatedRect box = cv::minAreaRect(outline);
    const double rimPx = 0.03 * std::max(box.size.width, box.size.height);
    const cv::Matx23d A = reg.affineAtlasFromImage();
    std::vector<cv::Point2d> pts, err;
    double sa = 0, sr = 0, si = 0;
    int nr = 0, ni = 0;
    for (const auto& l : truth.landmarks) {
        const cv::Point2d a(A(0, 0) * l.image.x + A(0, 1) * l.image.y + A(0, 2),
                            A(1, 0) * l.image.x + A(1, 1) * l.image.y + A(1, 2));
        sa += std::pow(cv::norm(a - l.atlas), 2);
        const cv::Point2d e = reg.atlasFromImage(l.image) - l.atlas;
        pts.push_back(l.image);
        err.push_back(e);
        const double d2 = e.dot(e);
        const cv::Point q(cvRound(l.image.x), cvRound(l.image.y));
        if (dist.at<float>(q) < rimPx) {
            sr += d2;
            ++nr;
        } else {
            si += d2;
            ++ni;
        }
    }
    const double n = std::max<double>(1, double(truth.landmarks.size()));
    d.affine = std::sqrt(sa / n);
    d.local = localPart(pts, err);
    d.rim = nr ? std::sqrt(sr / nr) : 0;
    d.interior = ni ? std::sqrt(si / ni) : 0;
    return d;
}

struct Row {
    double truthNonAffine = 0; ///< nonAffineRms of the case's truth
    Diagnosis diag;            ///< filled with --diagnose
    std::string family;
    std::string method;
    bool damaged = false;
    bool failed = false; ///< the method returned no result at all
    bench::Errors err;
    double seconds = 0;
};

double median(std::vector<double> v) {
    if (v.empty())
        return 0;
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
}

struct Summary {
    int n = 0, gross = 0;
    double rmse = 0, med = 0, mx = 0, worst = 0, seconds = 0;
};

Summary summarise(const std::vector<const Row*>& g) {
    Summary s;
    std::vector<double> secs;
    for (const Row* r : g) {
        s.rmse += r->err.rmse;
        s.med += r->err.median;
        s.mx += r->err.max;
        s.worst = std::max(s.worst, r->err.max);
        if (r->failed || r->err.max > 25)
            ++s.gross;
        secs.push_back(r->seconds);
    }
    s.n = int(g.size());
    if (s.n) {
        s.rmse /= s.n;
        s.med /= s.n;
        s.mx /= s.n;
    }
    s.seconds = median(secs);
    return s;
}

/// One line per family and clean/damaged: slicestation and elastix side by side.
void printTable(const std::vector<Row>& rows) {
    std::map<std::tuple<std::string, bool, std::string>, std::vector<const Row*>> groups;
    std::vector<std::string> families;
    for (const auto& r : rows) {
        groups[{r.family, r.damaged, r.method}].push_back(&r);
        if (std::find(families.begin(), families.end(), r.family) == families.end())
            families.push_back(r.family);
    }
    std::printf("\n%-8s %-8s | %-56s | %-56s\n", "", "", "slicestation", "elastix");
    std::printf("%-8s %-8s |%4s %6s %6s %6s %6s %5s %8s |%4s %6s %6s %6s %6s %5s %8s\n", "family",
                "sections", "n", "RMSE", "median", "max", "worst", "gross", "med s", "n", "RMSE",
                "median", "max", "worst", "gross", "med s");
    for (const auto& f : families)
        for (bool damaged : {false, true}) {
            const auto ours = groups.find({f, damaged, "ours"});
            if (ours == groups.end())
                continue;
            const Summary a = summarise(ours->second);
            std::printf("%-8s %-8s |%4d %6.2f %6.2f %6.2f %6.2f %5d %8.3f |", f.c_str(),
                        damaged ? "damaged" : "clean", a.n, a.rmse, a.med, a.mx, a.worst, a.gross,
                        a.seconds);
            const auto el = groups.find({f, damaged, "elastix"});
            if (el == groups.end()) {
                std::printf("%4s\n", "-");
                continue;
            }
            const Summary b = summarise(el->second);
            std::printf("%4d %6.2f %6.2f %6.2f %6.2f %5d %8.3f\n", b.n, b.rmse, b.med, b.mx,
                        b.worst, b.gross, b.seconds);
        }
    std::printf("(errors in atlas pixels, averages over sections of each section's RMSE, median "
                "and max landmark error; worst = largest max; gross = max over 25 px or no "
                "result; med s = median seconds per section, ours in process, elastix as "
                "processes)\n");
}

/// --series-run: the flags of a family's cases alone and judged live in the run, each with what
/// the two sections before it show (pipeline::shownInSeries, judgeInSeries), as the station
/// judges them. `sections` in case order; a family's run is its own.
template <typename Section> void printSeriesRun(const std::vector<Section>& sections) {
    const pipeline::SeriesContextParams params;
    const pipeline::DamageParams dp;
    std::printf("\nseries run (case i on plane i; live context: %d earlier sections):\n",
                params.window);
    // Per family: [damaged, clean][total, alone, live with gaps only, live with gaps and glass]
    std::map<std::string, std::array<std::array<int, 4>, 2>> counts;
    std::vector<std::string> order;
    const auto flagged = [](const pipeline::Registration& r) {
        return r.damageVerdict == pipeline::DamageVerdict::Damaged;
    };
    for (std::size_t i = 0; i < sections.size(); ++i) {
        const Section& s = sections[i];
        if (!counts.count(s.family))
            order.push_back(s.family);
        auto& c = counts[s.family][s.truth ? 0 : 1];
        std::vector<pipeline::SectionShown> gaps, shown;
        for (std::size_t k = i; k > 0 && shown.size() < std::size_t(params.window) &&
                                sections[k - 1].family == s.family;
             --k) {
            shown.push_back(pipeline::shownInSeries(sections[k - 1].reg));
            gaps.push_back({shown.back().gaps, {}});
        }
        pipeline::Registration byGaps = s.reg, live = s.reg;
        pipeline::judgeInSeries(byGaps, gaps, dp, params);
        pipeline::judgeInSeries(live, shown, dp, params);
        const bool judged[3] = {flagged(s.reg), flagged(byGaps), flagged(live)};
        ++c[0];
        for (int j = 0; j < 3; ++j)
            c[std::size_t(j + 1)] += judged[j];
        if (judged[0] != judged[1] || judged[0] != judged[2])
            std::printf("  %s case %d (%s): alone %.3f, live with the gaps %.3f, with gaps and "
                        "glass %.3f\n",
                        s.family.c_str(), s.index, s.truth ? "damaged" : "clean", s.reg.damageScore,
                        byGaps.damageScore, live.damageScore);
    }
    for (const std::string& f : order) {
        const auto& c = counts[f];
        std::printf("series run %-8s damaged caught alone / live with the earlier gaps / with "
                    "gaps and glass: %d / %d / %d of %d; clean flagged %d / %d / %d of %d\n",
                    f.c_str(), c[0][1], c[0][2], c[0][3], c[0][0], c[1][1], c[1][2], c[1][3],
                    c[1][0]);
    }
}

/// Fills `polygon` (pixel coordinates, rounded) into `mask` with 255.
void fillPolygon(cv::Mat& mask, const std::vector<cv::Point2f>& polygon) {
    std::vector<cv::Point> rounded;
    for (const cv::Point2f& p : polygon)
        rounded.emplace_back(cvRound(p.x), cvRound(p.y));
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{rounded}, cv::Scalar(255));
}

/// The decision rule (pipeline::isDamaged, default parameters) applied to the true damage:
/// each removed region's share of the tissue, its length against the tissue's width and its
/// thickness (twice the largest inscribed radius).
bool damagedByRule(const sim::GroundTruth& truth) {
    const std::vector<cv::Point2f> all = pipeline::outerContourPoints(truth.tissueMask);
    if (all.empty())
        return false;
    const cv::RotatedRect box = cv::minAreaRect(all);
    const double width = std::max(box.size.width, box.size.height);
    const double tissue = std::max(1, cv::countNonZero(truth.tissueMask));
    std::vector<pipeline::DamageRegion> regions;
    for (const auto& t : truth.damage) {
        if (t.polygon.size() < 3)
            continue;
        pipeline::DamageRegion r;
        r.kind = t.kind == sim::DamageKind::Tear       ? pipeline::DamageKind::Tear
                 : t.kind == sim::DamageKind::Fragment ? pipeline::DamageKind::Fragment
                 : t.kind == sim::DamageKind::Fold     ? pipeline::DamageKind::Fold
                                                       : pipeline::DamageKind::Missing;
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
        if (r.method != "ours")
            continue;
        (r.damaged ? damaged : clean) += r.err.rmse;
        ++(r.damaged ? nd : nc);
    }
    std::printf("\ndamage flag: %s\n", flagScore(d, &DamageRow::truth).c_str());
    int checkClean = 0, checkDamaged = 0;
    for (const auto& r : d)
        (r.truth ? checkDamaged : checkClean) += r.checkRegistration;
    std::printf("  check_registration (not a flag): %d clean, %d damaged\n", checkClean,
                checkDamaged);
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

/// Applies "key=value" settings (`set(key, value)` false on an unknown key); false on a setting
/// without '=' or with an unknown key.
template <class Set> bool applySettings(const std::vector<std::string>& settings, Set set) {
    for (const std::string& kv : settings) {
        const size_t eq = kv.find('=');
        if (eq == std::string::npos || !set(kv.substr(0, eq), std::atof(kv.c_str() + eq + 1)))
            return false;
    }
    return true;
}

/// The dense refinement's options for choosing them (`--dense`).
bool applyDenseSettings(const std::vector<std::string>& settings, pipeline::DenseRefineOptions& o) {
    return applySettings(settings, [&o](const std::string& key, double v) {
        if (key == "grid")
            o.gridMaxSide = int(v);
        else if (key == "sigma")
            o.levels.back().imageSigma = v;
        else if (key == "window")
            o.levels.back().window = int(v);
        else if (key == "iterations")
            o.levels.back().iterations = int(v);
        else if (key == "prior")
            o.priorAtlasPx = v;
        else if (key == "step")
            o.maxStepGridPx = v;
        else if (key == "min-gain")
            o.minGain = v;
        else if (key == "hold-out")
            o.holdOutBlockPx = int(v);
        else if (key == "field-sigma")
            o.fieldSigma = v;
        else if (key == "bias")
            o.biasSigma = v;
        else if (key == "robust-k")
            o.robustK = v;
        else
            return false;
        return true;
    });
}

/// The smooth warp's options for choosing them (`--smooth-opt`).
bool applySmoothSettings(const std::vector<std::string>& settings, pipeline::SmoothWarpOptions& o) {
    return applySettings(settings, [&o](const std::string& key, double v) {
        if (key == "spacing")
            o.nodeSpacing = v;
        else if (key == "stiffness")
            o.stiffness = v;
        else if (key == "robust-k")
            o.robustK = v;
        else if (key == "thinning")
            o.thinning = v;
        else
            return false;
        return true;
    });
}

/// The intensity affine's options for choosing them (`--intensity-opt`).
bool applyIntensitySettings(const std::vector<std::string>& settings,
                            pipeline::RegistrationOptions& ro) {
    pipeline::IntensityAffineOptions& o = ro.intensity;
    return applySettings(settings, [&o, &ro](const std::string& key, double v) {
        if (key == "edge-warp")
            ro.edgeWarpAfterIntensity = v != 0;
        else if (key == "grid")
            o.gridMaxSide = int(v);
        else if (key == "coarsest") {
            // Levels halve from this sigma down to the finest.
            const double finest = o.levelSigmas.back();
            o.levelSigmas.clear();
            for (double sg = v; sg > finest * 1.01; sg /= 2)
                o.levelSigmas.push_back(sg);
            o.levelSigmas.push_back(finest);
        } else if (key == "finest")
            o.levelSigmas.back() = v;
        else if (key == "iterations")
            o.iterations = int(v);
        else if (key == "robust-k")
            o.robustK = v;
        else if (key == "damping")
            o.damping = v;
        else if (key == "step")
            o.maxStepGridPx = v;
        else if (key == "min-gain")
            o.minGain = v;
        else if (key == "hold-out")
            o.holdOutBlockPx = int(v);
        else
            return false;
        return true;
    });
}

/// The intensity warp's options for choosing them (`--iwarp-opt`). `levels` = 1, 2 or 3 sets
/// the levels from `coarsest` spacing (halving) with sigmas 4, 2, 1 (the finest 1).
bool applyIntensityWarpSettings(const std::vector<std::string>& settings,
                                pipeline::IntensityWarpOptions& o) {
    int levels = int(o.levels.size());
    double coarsest = o.levels.front().spacingGridPx;
    int iterations = o.levels.front().iterations;
    const bool ok = applySettings(settings, [&](const std::string& key, double v) {
        if (key == "grid")
            o.gridMaxSide = int(v);
        else if (key == "levels")
            levels = std::clamp(int(v), 1, 3);
        else if (key == "coarsest")
            coarsest = v;
        else if (key == "iterations")
            iterations = int(v);
        else if (key == "stiffness")
            o.stiffness = v;
        else if (key == "damping")
            o.damping = v;
        else if (key == "robust-k")
            o.robustK = v;
        else if (key == "step")
            o.maxStepGridPx = v;
        else if (key == "local")
            o.localSigmaGridPx = v;
        else if (key == "min-gain")
            o.minGain = v;
        else if (key == "hold-out")
            o.holdOutBlockPx = int(v);
        else if (key == "refit")
            o.refitOnAll = v != 0;
        else if (key == "anchor") // 0: lattice and blocks at the grid's corner, as before
            o.origin = v != 0 ? std::nullopt : std::optional<cv::Point2d>(cv::Point2d(0, 0));
        else
            return false;
        return true;
    });
    o.levels.clear();
    for (int l = 0; l < levels; ++l)
        o.levels.push_back({double(1 << (levels - 1 - l)), coarsest / double(1 << l), iterations});
    return ok;
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
    app.add_option("--only", only,
                   "Run only these case indices of the --cases set (to look into them)");
    std::string overlayDir, refineMode = "on", nonLinearMode = "on", smoothMode = "on";
    std::string damageLogPath;
    bool listMissed = false;
    std::string mirroredGaps = "on";
    std::string foldCrease = "on";
    app.add_option("--fold-crease", foldCrease,
                   "DamageParams::foldFromCrease: a fold's band from the crease as deep as the gap "
                   "(off: a band as deep as the gap all round it)")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--mirrored-gaps", mirroredGaps,
                   "DamageParams::leaveOutMirroredGaps: gaps with a mirrored twin left out")
        ->check(CLI::IsMember({"on", "off"}));
    int foldRepairs = pipeline::RegistrationOptions{}.foldRepairs;
    app.add_option("--fold-repairs", foldRepairs,
                   "RegistrationOptions::foldRepairs: rounds of relaxing the final warp where "
                   "its map folds (0: keep the folds)")
        ->check(CLI::Range(0, 10));
    std::string crackPieces = "on";
    app.add_option("--crack-pieces", crackPieces,
                   "DamageParams::crackPieceFrac: a tear followed across a break to the pieces of "
                   "crack beyond it (off: crackPieceFrac 0)")
        ->check(CLI::IsMember({"on", "off"}));
    bool diagnoseErrors = false;
    std::vector<std::string> smoothSettings;
    app.add_option(
        "--smooth-opt", smoothSettings,
        "Smooth warp options as key=value (spacing, stiffness, robust-k, thinning), for choosing "
        "them");
    std::string templateIntensity = "off";
    app.add_option("--template-intensity", templateIntensity,
                   "Give ours the nearest 100 um average-template plane (elastix's moving image, "
                   "on the labels' 25 um grid) as the atlas intensity: off | template (template "
                   "family only) | all (every family)")
        ->check(CLI::IsMember({"off", "template", "all"}));
    std::vector<std::string> intensitySettings;
    app.add_option("--intensity-opt", intensitySettings,
                   "Intensity affine options as key=value (edge-warp 0/1, grid, coarsest, finest, "
                   "iterations, "
                   "robust-k, damping, step, min-gain, hold-out), for choosing them; finest "
                   "before coarsest");
    std::string intensityAffineMode = "on";
    app.add_option("--intensity-affine", intensityAffineMode,
                   "The intensity affine of ours (runs only with an atlas intensity plane, see "
                   "--template-intensity): on | off")
        ->check(CLI::IsMember({"on", "off"}));
    std::vector<std::string> iwarpSettings;
    app.add_option("--iwarp-opt", iwarpSettings,
                   "Intensity warp options as key=value (grid, levels, coarsest, iterations, "
                   "stiffness, damping, robust-k, step, local, min-gain, hold-out, refit 0/1, "
                   "anchor 0/1), for choosing them");
    std::string intensityWarpMode = "on";
    app.add_option("--intensity-warp", intensityWarpMode,
                   "The intensity warp of ours (runs only with an atlas intensity plane): on | off")
        ->check(CLI::IsMember({"on", "off"}));
    std::vector<std::string> rwarpSettings;
    app.add_option("--rwarp-opt", rwarpSettings,
                   "Region warp options as key=value (those of --iwarp-opt, and glass=0|1, "
                   "min-region), for choosing them");
    std::string regionLabelsText = "all";
    app.add_option("--region-labels", regionLabelsText,
                   "Labels the region warp paints: all (every Allen id, when the atlas has them) "
                   "or given (the labels the registration gets)")
        ->check(CLI::IsMember({"all", "given"}));
    // Off by default: the default figures are the product's with the built-in atlas or a stack
    // of major regions cut before its slices kept every id; slicectl and the daemon run it for
    // a stack cut from a volume (`--regions all`, and `--regions major` with its id planes),
    // which --region-warp on --region-labels all stands for.
    std::string regionWarpMode = "off";
    std::string edgeWithRegions =
        pipeline::RegistrationOptions{}.edgeWarpWithRegions ? "on" : "off";
    app.add_option("--edge-warp-with-regions", edgeWithRegions,
                   "RegistrationOptions::edgeWarpWithRegions: the edge warps (smooth, Laplace) "
                   "before the region warp when it runs: on | off (default: the product's)")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--region-warp", regionWarpMode,
                   "The region warp of ours (runs only without an atlas intensity plane and "
                   "with fine labels, as slicectl and the daemon run it for a stack cut from "
                   "a volume; --region-labels all gives them here): on | off")
        ->check(CLI::IsMember({"on", "off"}));
    std::vector<std::string> denseSettings;
    app.add_option("--dense", denseSettings,
                   "Dense refinement options as key=value (grid, sigma, window, iterations, "
                   "prior, step, min-gain, hold-out, field-sigma, bias, robust-k), for choosing "
                   "them");
    app.add_flag("--diagnose", diagnoseErrors,
                 "Print where each case's error lies (affine, best affine, the part no cubic "
                 "field fixes, outline rim and interior) and their averages");
    app.add_option("--nonlinear", nonLinearMode,
                   "Ours with its non-linear stages (Laplace warp, dense refinement): on | off "
                   "(off: the affine alone)")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--smooth", smoothMode,
                   "The smooth (B-spline) warp of ours: on (the default, as the product) | off")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--refine", refineMode, "Dense refinement of ours: on | off")
        ->check(CLI::IsMember({"on", "off"}));
    app.add_option("--damage-log", damageLogPath,
                   "Write a row per reported damage region (its measures, the registration's "
                   "confidence around it and how much of it is painted damage) here");
    bool seriesRun = false;
    app.add_flag("--series-run", seriesRun,
                 "Damage in a run (issue 18, item 5): each family's cases cut from neighbouring "
                 "planes in order (case i on loaded plane i, the planes spread evenly over the "
                 "AP range), then judged again with the series context as the station does "
                 "(the gaps and glass of the two earlier sections); prints flags alone and live");
    double maxRotationDeg = -1;
    app.add_option("--max-rotation", maxRotationDeg,
                   "Sections turned uniformly within +-this many degrees (180: any way up; "
                   "default: each generator's own range, 20 or 25)")
        ->check(CLI::Range(0.0, 180.0));
    std::string seriesAnatomy = "family";
    app.add_option("--series-anatomy", seriesAnatomy,
                   "With --series-run: family (each case's own anatomy models) or ventricles "
                   "(every first-generator case's ventricles grown by 0.014 of the tissue width, "
                   "the middle of family 1m's range, no fissure opened: one brain with enlarged "
                   "ventricles throughout the run)")
        ->check(CLI::IsMember({"family", "ventricles"}));
    app.add_flag("--list-missed", listMissed,
                 "Print each true damage region no reported region overlaps (a tenth of it)");
    app.add_option("--overlays", overlayDir,
                   "Write each case's overlay (ours, damage in red) here");
    std::string familyText = "all", labelsText = "major";
    app.add_option("--family", familyText,
                   "Generator family: 1 (first), 2 (second, written apart), template (second "
                   "family rendered from the Allen average template), 1m (first family with "
                   "issue 18's damage models and not-damage anatomy; not in all) or all")
        ->check(CLI::IsMember({"1", "2", "template", "1m", "all"}));
    app.add_option("--labels", labelsText,
                   "Atlas the registration gets: major (the 20 collapsed regions, as always) or "
                   "all (every Allen id) or all-plain (every Allen id, and nothing told about "
                   "which ids are ventricles or separate parts: a label image without its "
                   "ontology, as slicectl register --atlas LABELS.tif gets it) or "
                   "all-ventricles (every Allen id, told only which are ventricles)")
        ->check(CLI::IsMember({"major", "all", "all-plain", "all-ventricles"}));
    CLI11_PARSE(app, argc, argv);
    FILE* damageLog = damageLogPath.empty() ? nullptr : std::fopen(damageLogPath.c_str(), "w");
    if (damageLog)
        std::fprintf(damageLog, "family,case,damaged,flag,kind,share,length_w,thick_w,open,score,"
                                "ring_confidence,painted,level_share,level_noise,excess,"
                                "excess_ventricle,misfit\n");
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
    if (useElastix && atlas->templatePlanes100.empty()) {
        std::cerr << "elastix needs the real atlas template; skipping elastix\n";
        useElastix = false;
    }
    const bool allLabels = labelsText.rfind("all", 0) == 0;
    if (allLabels && atlas->name != "allen-ccf-25um") {
        std::cerr << "--labels all needs the Allen atlas under --shared\n";
        return 1;
    }
    // With every Allen id the registration is told which ids are ventricles and which belong to
    // the separate parts, as the major-region defaults do for the collapsed ids: atlas
    // knowledge, nothing the generators know.
    pipeline::RegistrationOptions regOptions;
    regOptions.damage.leaveOutMirroredGaps = mirroredGaps == "on";
    regOptions.damage.foldFromCrease = foldCrease == "on";
    regOptions.foldRepairs = foldRepairs;
    if (crackPieces == "off")
        regOptions.damage.crackPieceFrac = 0;
    if (labelsText == "all" || labelsText == "all-ventricles") {
        const pipeline::RegistrationOptions defaults;
        regOptions.ventricleIds.clear();
        for (auto& part : regOptions.separateParts)
            part.clear();
        if (labelsText == "all-ventricles")
            regOptions.separateParts = defaults.separateParts;
        for (const auto& st : atlas->ontology.structures()) {
            const auto id = static_cast<std::int32_t>(st.id);
            if (atlas->ontology.isDescendantOf(st.id, 73))
                regOptions.ventricleIds.push_back(id);
            for (size_t p = 0; labelsText == "all" && p < defaults.separateParts.size(); ++p)
                for (std::int32_t top : defaults.separateParts[p])
                    if (atlas->ontology.isDescendantOf(st.id, std::uint32_t(top)))
                        regOptions.separateParts[p].push_back(id);
        }
    }
    const bool fineRegionLabels =
        regionLabelsText == "all" && !allLabels && atlas->fullPlanes.size() == atlas->planes.size();
    if (fineRegionLabels) {
        for (const auto& st : atlas->ontology.structures())
            if (atlas->ontology.isDescendantOf(st.id, 73))
                regOptions.regionWarpOptions.glassIds.push_back(static_cast<std::int32_t>(st.id));
    } else {
        regOptions.regionWarpOptions.glassIds = regOptions.ventricleIds;
    }
    if (!applySmoothSettings(smoothSettings, regOptions.smooth)) {
        std::cerr << "bad --smooth-opt setting\n";
        return 2;
    }
    regOptions.intensityWarp = intensityWarpMode == "on";
    if (!iwarpSettings.empty() &&
        !applyIntensityWarpSettings(iwarpSettings, regOptions.intensityWarpOptions)) {
        std::cerr << "bad --iwarp-opt setting\n";
        return 2;
    }
    regOptions.regionWarp = regionWarpMode == "on";
    regOptions.edgeWarpWithRegions = edgeWithRegions == "on";
    {
        // glass= and min-region= are the region warp's own; the rest are the field's.
        std::vector<std::string> fieldSettings;
        bool ok = true;
        for (const std::string& kv : rwarpSettings) {
            if (kv.rfind("glass=", 0) == 0)
                regOptions.regionWarpOptions.glassLike = std::stoi(kv.substr(6)) != 0;
            else if (kv.rfind("min-region=", 0) == 0)
                regOptions.regionWarpOptions.minRegionPx = std::stoi(kv.substr(11));
            else if (kv.rfind("max-spread=", 0) == 0)
                regOptions.regionWarpOptions.maxInnerSpread = std::stod(kv.substr(11));
            else
                fieldSettings.push_back(kv);
        }
        if (!fieldSettings.empty())
            ok = applyIntensityWarpSettings(fieldSettings, regOptions.regionWarpOptions.warp);
        if (!ok) {
            std::cerr << "bad --rwarp-opt setting\n";
            return 2;
        }
    }
    if (!applyIntensitySettings(intensitySettings, regOptions)) {
        std::cerr << "bad --intensity-opt setting\n";
        return 2;
    }
    regOptions.intensityAffine = intensityAffineMode == "on";
    if (!applyDenseSettings(denseSettings, regOptions.dense) ||
        !applyDenseSettings(denseSettings, regOptions.denseWithIntensity)) {
        std::cerr << "bad --dense setting\n";
        return 2;
    }
    std::vector<bench::BenchCase> all;
    const int planeCount = static_cast<int>(atlas->planes.size());
    if (familyText == "1" || familyText == "all")
        for (auto& c : bench::makeCases(cases, planeCount, {w, h}))
            all.push_back(c);
    if (familyText == "1m")
        for (auto& c : bench::makeCasesModels(cases, planeCount, {w, h}))
            all.push_back(c);
    if (familyText == "2" || familyText == "all")
        for (auto& c : bench::makeCasesB(cases, planeCount, {w, h}))
            all.push_back(c);
    if ((familyText == "template" || familyText == "all")) {
        if (atlas->templatePlanes.empty()) {
            std::cerr << "the template family needs average_template_100.nrrd under --shared\n";
            if (familyText == "template")
                return 1;
        } else {
            for (auto& c : bench::makeCasesTemplate(cases, planeCount, {w, h}))
                all.push_back(c);
        }
    }
    std::printf("atlas: %s, %zu planes; %d cases per family of %dx%d px; families: %s; labels "
                "given: %s; elastix: %s; template mirrored against QuickNII: %s\n",
                atlas->name.c_str(), atlas->planes.size(), cases, w, h, familyText.c_str(),
                labelsText.c_str(), useElastix ? "yes" : "no",
                atlas->templateMirrored ? "yes" : "no");

    std::ofstream csv;
    if (!csvPath.empty()) {
        csv.open(csvPath);
        csv << "family,case,method,damaged,stain,rmse,median,max,seconds,failed\n";
    }
    if (maxRotationDeg >= 0)
        for (auto& c : all) {
            c.options.maxRotationDeg = maxRotationDeg;
            c.optionsB.maxRotationDeg = maxRotationDeg;
        }
    if (seriesRun)
        for (auto& c : all) {
            c.plane = c.index % planeCount;
            if (seriesAnatomy == "ventricles" && bench::firstGenerator(c.family)) {
                c.options.anatomy.ventricleGrowthFrac = 0.014;
                c.options.anatomy.fissureOpenFrac = 0;
            }
        }
    // --series-run: each case's registration and truth, in case order per family.
    struct RunSection {
        std::string family;
        int index = 0;
        bool truth = false;
        pipeline::Registration reg;
    };
    std::vector<RunSection> run;
    std::vector<Row> rows;
    std::map<std::string, std::vector<DamageRow>> damageRows;
    for (auto& c : all) {
        if (!only.empty() && std::find(only.begin(), only.end(), c.index) == only.end())
            continue;
        const std::string family = bench::familyName(c.family);
        const cv::Mat& plane =
            allLabels ? atlas->fullPlanes[size_t(c.plane)] : atlas->planes[size_t(c.plane)];
        auto gen = bench::generate(c, *atlas);
        if (!gen) {
            std::cerr << c.describe() << ": generator failed: " << gen.error().message << "\n";
            return 1;
        }
        std::vector<cv::Point2d> pts;
        for (const auto& l : gen->truth.landmarks)
            pts.push_back(l.image);

        Row ours;
        ours.truthNonAffine = nonAffineRms(gen->truth.landmarks);
        ours.family = family;
        ours.method = "ours";
        ours.damaged = c.damaged();
        const auto t0 = std::chrono::steady_clock::now();
        pipeline::RegistrationOptions ro = regOptions;
        ro.denseRefine = refineMode == "on" && nonLinearMode == "on";
        ro.nonLinear = nonLinearMode == "on";
        ro.smoothWarp = smoothMode == "on";
        if (templateIntensity == "all" ||
            (templateIntensity == "template" && c.family == bench::Family::Template))
            ro.atlasIntensity = bench::templateOnLabelGrid(*atlas, c.plane, plane.size());
        ro.regionLabels = fineRegionLabels ? atlas->fullPlanes[size_t(c.plane)] : plane;
        auto reg = pipeline::registerSection(gen->image, plane, ro);
        ours.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (reg) {
            std::vector<cv::Point2d> mapped;
            for (const auto& p : pts)
                mapped.push_back(reg->atlasFromImage(p));
            ours.err = bench::landmarkErrors(gen->truth.landmarks, mapped);
            if (diagnoseErrors) {
                ours.diag = diagnose(gen->truth, *reg);
                std::fprintf(stderr,
                             "%-45s diag affine %.2f best-affine %.2f final %.2f local %.2f rim "
                             "%.2f interior %.2f\n",
                             c.describe().c_str(), ours.diag.affine, ours.diag.best, ours.err.rmse,
                             ours.diag.local, ours.diag.rim, ours.diag.interior);
            }
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
            // A model with no place to paint (no ventricle to tear) leaves the 1m case clean.
            d.truth = c.damaged() &&
                      (c.family != bench::Family::FirstModels || !gen->truth.damage.empty());
            d.flagged = reg->damaged;
            d.checkRegistration = reg->damageVerdict == pipeline::DamageVerdict::CheckRegistration;
            for (const auto& [name, ms] : reg->timingsMs)
                if (name.rfind("damage", 0) == 0)
                    d.ms += ms;
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
                if (cv::countNonZero(truthMask & reported) >= 0.1 * area)
                    ++d.overlapped;
                else if (listMissed)
                    std::printf("missed region: %s case %d, %s of %d px (section %s)\n",
                                family.c_str(), c.index, sim::toString(t.kind).data(), area,
                                reg->damaged ? "flagged" : "not flagged");
            }
            damageRows[family].push_back(d);
            if (seriesRun)
                run.push_back({family, c.index, d.truth, *reg});
            if (damageLog) {
                cv::Mat truthAll = cv::Mat::zeros(gen->image.size(), CV_8U);
                for (const auto& t : gen->truth.damage)
                    fillPolygon(truthAll, t.polygon);
                for (const auto& r : reg->damage) {
                    cv::Mat m = cv::Mat::zeros(gen->image.size(), CV_8U);
                    fillPolygon(m, r.polygon);
                    const double area = std::max(1, cv::countNonZero(m));
                    const double painted = cv::countNonZero(m & truthAll) / area;
                    double conf = -1;
                    if (!reg->confidence.empty()) {
                        cv::Mat small;
                        cv::resize(m, small, reg->confidence.size(), 0, 0, cv::INTER_NEAREST);
                        cv::Mat ring;
                        cv::dilate(small, ring,
                                   cv::getStructuringElement(cv::MORPH_ELLIPSE, {9, 9}));
                        ring &= ~small;
                        ring &= reg->confidence > 0;
                        if (cv::countNonZero(ring) > 0)
                            conf = cv::mean(reg->confidence, ring)[0];
                    }
                    const double bw = std::max(1.0, reg->brainWidthPx);
                    std::fprintf(damageLog,
                                 "%s,%d,%d,%s,%s,%.5f,%.4f,%.4f,%.3f,%.3f,%.3f,%.3f,%.3f,%.1f,"
                                 "%.3f,%.3f,%d\n",
                                 family.c_str(), c.index, int(d.truth),
                                 d.flagged ? "flag" : (d.checkRegistration ? "check" : "-"),
                                 std::string(pipeline::toString(r.kind)).c_str(), r.share,
                                 r.lengthPx / bw, r.thicknessPx / bw, r.openShare, r.score, conf,
                                 painted, r.levelShare, r.levelNoiseUnits, r.excessShare,
                                 r.excessVentricleShare, int(r.misfit));
                }
            }
            if (!overlayDir.empty()) {
                const cv::Mat tile = pipeline::renderOverlay(*reg, plane);
                std::filesystem::create_directories(overlayDir);
                const auto path = std::filesystem::path(overlayDir) /
                                  ("f" + family + "-case-" + std::to_string(c.index) + ".png");
                if (auto written = core::writeImage(path, tile); !written)
                    std::cerr << path << ": " << written.error().message << "\n";
            }
            char refined[64];
            std::snprintf(refined, sizeof refined, " | explained %.3f -> %.3f%s | min J %.2f",
                          reg->quality.explainedBeforeRefine, reg->quality.explainedAfterRefine,
                          reg->quality.refined ? " kept" : "", reg->quality.minJacobian);
            steps += refined;
            if (ro.intensityAffine && !ro.atlasIntensity.empty()) {
                std::snprintf(refined, sizeof refined, " | intensity %.3f -> %.3f%s",
                              reg->quality.intensityExplainedBefore,
                              reg->quality.intensityExplainedAfter,
                              reg->quality.intensityAffineKept ? " kept" : "");
                steps += refined;
            }
            if (ro.intensityWarp && !ro.atlasIntensity.empty()) {
                std::snprintf(refined, sizeof refined, " | iwarp %.3f -> %.3f%s J %.2f",
                              reg->quality.intensityWarpExplainedBefore,
                              reg->quality.intensityWarpExplainedAfter,
                              reg->quality.intensityWarpKept ? " kept" : "",
                              reg->quality.minJacobian);
                steps += refined;
            }
            if (ro.regionWarp && ro.atlasIntensity.empty() && !ro.regionLabels.empty()) {
                std::snprintf(refined, sizeof refined, " | rwarp %.3f -> %.3f%s J %.2f",
                              reg->quality.regionWarpExplainedBefore,
                              reg->quality.regionWarpExplainedAfter,
                              reg->quality.regionWarpKept ? " kept" : "", reg->quality.minJacobian);
                steps += refined;
            }
            steps += " | damage " +
                     std::string(d.flagged             ? "FLAGGED "
                                 : d.checkRegistration ? "CHECK "
                                                       : "clean ") +
                     d.kinds;
        }
        std::fprintf(stderr, "%-45s ours    rmse %6.2f max %6.2f  %.3f s (ms:%s)\n",
                     c.describe().c_str(), ours.err.rmse, ours.err.max, ours.seconds,
                     steps.c_str());

        if (useElastix && (elastixCases < 0 || c.index < elastixCases)) {
            const cv::Mat moving = bench::templatePlane100(*atlas, c.plane);
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
            const auto out =
                bench::runElastix(in, std::filesystem::path(workDir) /
                                          ("f" + family + "case" + std::to_string(c.index)));
            Row el;
            el.family = family;
            el.method = "elastix";
            el.damaged = c.damaged();
            el.seconds = out.seconds;
            if (out.ok) {
                std::vector<cv::Point2d> mapped;
                for (const auto& m : out.mappedUm)
                    mapped.push_back(m * (1.0 / atlas->umPerPx));
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
            for (auto it = rows.end() - (rows.back().method == "elastix" ? 2 : 1); it != rows.end();
                 ++it)
                csv << family << ',' << c.index << ',' << it->method << ',' << it->damaged << ','
                    << (c.brightfield() ? "brightfield" : "fluorescence") << ',' << it->err.rmse
                    << ',' << it->err.median << ',' << it->err.max << ',' << it->seconds << ','
                    << it->failed << '\n';
        }
    }
    printTable(rows);
    if (seriesRun)
        printSeriesRun(run);
    std::map<std::string, std::pair<double, int>> nonAffine;
    for (const auto& r : rows)
        if (r.method == "ours") {
            nonAffine[r.family].first += r.truthNonAffine;
            ++nonAffine[r.family].second;
        }
    std::printf("non-linear part of the true maps (RMS distance of the true landmark positions "
                "from their best affine fit, atlas px), average per family:");
    for (const auto& [f, v] : nonAffine)
        std::printf(" %s %.2f", f.c_str(), v.first / v.second);
    std::printf("\n");
    if (diagnoseErrors) {
        std::map<std::string, std::array<double, 7>> sums;
        for (const auto& r : rows)
            if (r.method == "ours") {
                auto& a = sums[r.family + (r.damaged ? " damaged" : " clean")];
                const double v[6] = {r.diag.affine, r.diag.best, r.err.rmse,
                                     r.diag.local,  r.diag.rim,  r.diag.interior};
                for (int i = 0; i < 6; ++i)
                    a[size_t(i)] += v[i];
                a[6] += 1;
            }
        std::printf("\nwhere the error lies (averages of per-section RMSE, atlas px):\n%-18s "
                    "%7s %7s %7s %7s %7s %7s\n",
                    "", "affine", "best-aff", "final", "local", "rim", "interior");
        for (const auto& [name, a] : sums)
            std::printf("%-18s %7.2f %7.2f %7.2f %7.2f %7.2f %7.2f\n", name.c_str(), a[0] / a[6],
                        a[1] / a[6], a[2] / a[6], a[3] / a[6], a[4] / a[6], a[5] / a[6]);
    }
    for (const auto& [family, d] : damageRows) {
        std::vector<Row> familyRows;
        for (const auto& r : rows)
            if (r.family == family)
                familyRows.push_back(r);
        std::printf("\n-- family %s --", family.c_str());
        printDamage(d, familyRows);
    }
    return 0;
}
