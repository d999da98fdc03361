#include "slicestation/pipeline/dense_refine.hpp"

#include "slicestation/pipeline/mask_ops.hpp"
#include "stage_measures.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <unordered_map>

namespace slicestation::pipeline {
namespace {

/// Atlas labels as indices 0..K-1 (label 0, outside the brain, is always index 0), so that a
/// region's stain is a table look-up and labels can pass through cv::remap as floats.
struct LabelIndex {
    cv::Mat index; ///< CV_32F holding small integers, atlas size
    std::vector<std::int32_t> ids;
};

LabelIndex indexLabels(const cv::Mat& labels) {
    LabelIndex li;
    li.index.create(labels.size(), CV_32F);
    std::unordered_map<std::int32_t, int> lookup{{0, 0}};
    li.ids.push_back(0);
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* in = labels.ptr<std::int32_t>(y);
        float* out = li.index.ptr<float>(y);
        std::int32_t last = 0;
        int lastIndex = 0;
        for (int x = 0; x < labels.cols; ++x) {
            if (in[x] != last) {
                auto [it, added] = lookup.try_emplace(in[x], static_cast<int>(li.ids.size()));
                if (added)
                    li.ids.push_back(in[x]);
                last = in[x];
                lastIndex = it->second;
            }
            out[x] = static_cast<float>(lastIndex);
        }
    }
    return li;
}

/// The atlas painted with one stain level per region (plus b x the atlas intensity), on an atlas
/// copy reduced by `k`, blurred, with its gradient per atlas px.
struct Painted {
    cv::Mat j, jx, jy;
    int k = 1;
};

class Painter {
public:
    Painter(const LabelIndex& li, const cv::Mat& intensity, int k)
        : li_(li), intensity_(intensity), k_(k) {}

    /// Region k painted as c0[k] + cx[k] x + cy[k] y (atlas px), plus b x the intensity.
    Painted paint(const std::vector<float>& c0, const std::vector<float>& cx,
                  const std::vector<float>& cy, float b, double sigmaAtlasPx) const {
        cv::Mat img(li_.index.size(), CV_32F);
        for (int y = 0; y < img.rows; ++y) {
            const float* idx = li_.index.ptr<float>(y);
            float* out = img.ptr<float>(y);
            for (int x = 0; x < img.cols; ++x) {
                const auto k = static_cast<size_t>(idx[x]);
                out[x] = c0[k] + cx[k] * float(x) + cy[k] * float(y);
            }
        }
        if (!intensity_.empty() && b != 0)
            cv::scaleAdd(intensity_, b, img, img);
        Painted p;
        p.k = k_;
        if (k_ > 1) {
            // Pad to a multiple of k so that the reduction is exactly k on both axes.
            cv::copyMakeBorder(img, img, 0, (k_ - img.rows % k_) % k_, 0, (k_ - img.cols % k_) % k_,
                               cv::BORDER_REPLICATE);
            cv::resize(img, img, cv::Size(img.cols / k_, img.rows / k_), 0, 0, cv::INTER_AREA);
        }
        const double s = sigmaAtlasPx / k_;
        if (s > 0.3)
            cv::GaussianBlur(img, p.j, cv::Size(), s, s, cv::BORDER_REPLICATE);
        else
            p.j = img;
        cv::Sobel(p.j, p.jx, CV_32F, 1, 0, 1, 0.5 / k_, 0, cv::BORDER_REPLICATE);
        cv::Sobel(p.j, p.jy, CV_32F, 0, 1, 1, 0.5 / k_, 0, cv::BORDER_REPLICATE);
        return p;
    }

private:
    const LabelIndex& li_;
    const cv::Mat& intensity_;
    int k_;
};

/// Fitted stain model, by label index: region k is c0 + cx x + cy y at atlas pixel (x, y)
/// (a level, and a gradient when asked), plus b x the atlas intensity.
struct StainFit {
    std::vector<float> c0, cx, cy;
    float b = 0;
};

/// Weighted least squares of grey ~ c0[k] + cx[k] ax + cy[k] ay + b t for the label k at each
/// grid pixel (t empty = no intensity term; gradients only for regions seen on at least
/// `minGradientPx` weighted pixels), by a few alternations between the region terms and b.
StainFit fitStain(const cv::Mat& grey, const cv::Mat& idx, const cv::Mat& ax, const cv::Mat& ay,
                  const cv::Mat& w, const cv::Mat& t, size_t regions, bool gradients,
                  cv::Point2d origin) {
    constexpr double kMinGradientWeight = 100;
    constexpr double kUnit = 100; // atlas px: coordinates are (x - origin) / kUnit for conditioning
    StainFit f;
    f.c0.assign(regions, 0);
    f.cx.assign(regions, 0);
    f.cy.assign(regions, 0);
    const int rounds = t.empty() ? 1 : 3;
    std::vector<cv::Matx33d> normal(regions);
    std::vector<cv::Vec3d> rhs(regions);
    std::vector<double> swt(regions);
    for (int round = 0; round < rounds; ++round) {
        std::fill(normal.begin(), normal.end(), cv::Matx33d::zeros());
        std::fill(rhs.begin(), rhs.end(), cv::Vec3d());
        std::fill(swt.begin(), swt.end(), 0.0);
        double gw = 0, gwv = 0;
        for (int y = 0; y < grey.rows; ++y) {
            const float* g = grey.ptr<float>(y);
            const float* l = idx.ptr<float>(y);
            const float* ww = w.ptr<float>(y);
            const float* px = ax.ptr<float>(y);
            const float* py = ay.ptr<float>(y);
            const float* tt = t.empty() ? nullptr : t.ptr<float>(y);
            for (int x = 0; x < grey.cols; ++x) {
                if (ww[x] <= 0)
                    continue;
                const auto k = static_cast<size_t>(l[x]);
                const double v = g[x] - (tt ? f.b * tt[x] : 0.0f);
                const double u = (px[x] - origin.x) / kUnit, q = (py[x] - origin.y) / kUnit;
                const double a[3] = {1, u, q};
                cv::Matx33d& n = normal[k];
                for (int r = 0; r < 3; ++r) {
                    rhs[k][r] += ww[x] * v * a[r];
                    for (int c = r; c < 3; ++c)
                        n(r, c) += ww[x] * a[r] * a[c];
                }
                if (tt)
                    swt[k] += ww[x] * tt[x];
                gw += ww[x];
                gwv += ww[x] * v;
            }
        }
        const double global = gw > 0 ? gwv / gw : 0;
        for (size_t k = 0; k < regions; ++k) {
            cv::Matx33d& n = normal[k];
            for (int r = 0; r < 3; ++r)
                for (int c = 0; c < r; ++c)
                    n(r, c) = n(c, r);
            const double sw = n(0, 0);
            double c0 = global, cx = 0, cy = 0;
            if (gradients && sw >= kMinGradientWeight) {
                cv::Matx33d m = n;
                m(1, 1) += 1e-3 * sw; // a little ridge: a region seen along a thin strip
                m(2, 2) += 1e-3 * sw;
                cv::Vec3d sol;
                if (cv::solve(m, rhs[k], sol, cv::DECOMP_CHOLESKY)) {
                    c0 = sol[0];
                    cx = sol[1];
                    cy = sol[2];
                } else {
                    c0 = rhs[k][0] / sw;
                }
            } else if (sw > 1e-6) {
                c0 = rhs[k][0] / sw;
            }
            // Back to absolute atlas coordinates.
            f.cx[k] = float(cx / kUnit);
            f.cy[k] = float(cy / kUnit);
            f.c0[k] = float(c0 - cx * origin.x / kUnit - cy * origin.y / kUnit);
        }
        if (!t.empty() && round + 1 < rounds) {
            // b from the residual of the region terms, against t centred in each region.
            double num = 0, den = 0;
            for (int y = 0; y < grey.rows; ++y) {
                const float* g = grey.ptr<float>(y);
                const float* l = idx.ptr<float>(y);
                const float* ww = w.ptr<float>(y);
                const float* px = ax.ptr<float>(y);
                const float* py = ay.ptr<float>(y);
                const float* tt = t.ptr<float>(y);
                for (int x = 0; x < grey.cols; ++x) {
                    if (ww[x] <= 0)
                        continue;
                    const auto k = static_cast<size_t>(l[x]);
                    const double sw = std::max(normal[k](0, 0), 1e-6);
                    const double tc = tt[x] - swt[k] / sw;
                    const double model = f.c0[k] + f.cx[k] * px[x] + f.cy[k] * py[x];
                    const double res = g[x] - model - f.b * (swt[k] / sw);
                    num += ww[x] * res * tc;
                    den += ww[x] * tc * tc;
                }
            }
            f.b = den > 1e-9 ? float(num / den) : 0.0f;
        }
    }
    return f;
}

/// Smallest value of `det` / `ref` (`ref` non-zero, of either sign).
double minRelative(const cv::Mat& det, double ref) {
    double lo = 0, hi = 0;
    cv::minMaxLoc(det, &lo, &hi);
    return ref > 0 ? lo / ref : hi / ref;
}

/// Removes a smooth additive bias (uneven illumination, stain gradients across the section) from
/// the residual `r`: its weighted local mean at `sigma` grid px.
void removeBias(cv::Mat& r, const cv::Mat& w, double sigma) {
    if (sigma <= 0)
        return;
    // The bias is smooth: estimated on a copy reduced 4 times, which keeps the wide blur cheap.
    r -= weightedLocalMean(r, w, sigma, sigma >= 8 ? 4 : 1);
}

} // namespace

DenseRefinement refineDense(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                            const cv::Mat& mapY, const cv::Mat& atlasLabels,
                            const cv::Mat& atlasIntensity, const DenseRefineOptions& o) {
    CV_Assert(grey.type() == CV_32F && weight.type() == CV_8U && mapX.type() == CV_32F &&
              mapY.type() == CV_32F && atlasLabels.type() == CV_32S);
    CV_Assert(weight.size() == grey.size() && mapX.size() == grey.size() &&
              mapY.size() == grey.size());
    CV_Assert(atlasIntensity.empty() ||
              (atlasIntensity.type() == CV_32F && atlasIntensity.size() == atlasLabels.size()));
    CV_Assert(!o.levels.empty());

    DenseRefinement out;
    const cv::Size gs = grey.size();
    out.ux = cv::Mat::zeros(gs, CV_32F);
    out.uy = cv::Mat::zeros(gs, CV_32F);
    out.confidence = cv::Mat::zeros(gs, CV_32F);
    cv::Mat w;
    weight.convertTo(w, CV_32F, 1.0 / 255);
    cv::threshold(w, w, 0, 1, cv::THRESH_BINARY);
    if (cv::countNonZero(weight) < 64)
        return out;

    const LabelIndex li = indexLabels(atlasLabels);
    // A mirrored map (a section mounted face down) has negative determinants throughout: the
    // reference then carries the sign, so that relative values stay positive.
    const cv::Mat det0 = jacobianDet(mapX, mapY);
    const double refDet = percentile(det0, 0.5, weight);
    if (!(std::abs(refDet) > 1e-9))
        return out;
    const double s = std::sqrt(std::abs(refDet)); // atlas px per grid px
    const int k = std::max(1, static_cast<int>(std::floor(s)));
    const Painter painter(li, atlasIntensity, k);
    const cv::Point2d origin(atlasLabels.cols / 2.0, atlasLabels.rows / 2.0);

    cv::Mat ax, ay, rx, ry, idx, tGrid;
    auto sampleAt = [&](const cv::Mat& ux, const cv::Mat& uy) {
        ax = mapX + ux;
        ay = mapY + uy;
        cv::remap(li.index, idx, ax, ay, cv::INTER_NEAREST, cv::BORDER_CONSTANT, cv::Scalar(0));
        if (!atlasIntensity.empty())
            cv::remap(atlasIntensity, tGrid, ax, ay, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
        // Coordinates on the reduced painted atlas.
        const double inv = 1.0 / k;
        ax.convertTo(rx, CV_32F, inv, 0.5 * inv - 0.5);
        ay.convertTo(ry, CV_32F, inv, 0.5 * inv - 0.5);
    };
    auto predicted = [&](const Painted& p, cv::Mat& jw, cv::Mat* gx, cv::Mat* gy) {
        cv::remap(p.j, jw, rx, ry, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
        if (gx)
            cv::remap(p.jx, *gx, rx, ry, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
        if (gy)
            cv::remap(p.jy, *gy, rx, ry, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
    };
    // Explained share of the variance of the smoothed section (weights `w`) for a field.
    const DenseLevel& finest = o.levels.back();
    cv::Mat finestSmooth;
    cv::GaussianBlur(grey, finestSmooth, cv::Size(), finest.imageSigma, finest.imageSigma,
                     cv::BORDER_REPLICATE);
    // Held out: the field is fitted on half the pixels (a checkerboard of blocks) and judged on
    // the other half, so that a field that only fits the texture and noise is not kept.
    const HeldOutWeights held = heldOutWeights(w, o.holdOutBlockPx);
    const cv::Mat &wTrain = held.train, &wTest = held.test; // named: lambdas capture them
    const double meanI = weightedMean(finestSmooth, w);
    cv::Mat centred = finestSmooth - meanI;
    const double totalVar = std::max(1e-12, weightedMean(centred.mul(centred), w));
    auto residualSq = [&](const cv::Mat& ux, const cv::Mat& uy) {
        sampleAt(ux, uy);
        const StainFit f =
            fitStain(grey, idx, ax, ay, w, tGrid, li.ids.size(), o.regionGradients, origin);
        const Painted p = painter.paint(f.c0, f.cx, f.cy, f.b, finest.imageSigma * s);
        cv::Mat jw;
        predicted(p, jw, nullptr, nullptr);
        cv::Mat r = finestSmooth - jw;
        removeBias(r, w, o.biasSigma);
        return cv::Mat(r.mul(r));
    };
    const cv::Mat r2Before = residualSq(out.ux, out.uy);
    const double testVar = std::max(1e-12, weightedMean(centred.mul(centred), wTest));
    out.explainedBefore = 1 - weightedMean(r2Before, wTest) / testVar;
    {
        cv::Mat(idx).setTo(-1, weight == 0);
        std::vector<char> present(li.ids.size(), 0);
        for (int y = 0; y < idx.rows; ++y)
            for (int x = 0; x < idx.cols; ++x)
                if (const float v = idx.at<float>(y, x); v > 0)
                    present[size_t(v)] = 1;
        out.regions = static_cast<int>(std::count(present.begin(), present.end(), 1));
    }

    cv::Mat ux = out.ux.clone(), uy = out.uy.clone();
    double minRel = minRelative(det0, refDet);
    bool moved = false; // a step was taken: the field differs from the one measured before
    cv::Mat smooth, jw, gx, gy, r, wr, pxx, pxy, pyy, bx, by, dux, duy, cand1, cand2;
    for (const DenseLevel& level : o.levels) {
        if (level.iterations <= 0)
            continue; // measuring only (RegistrationOptions::refineAfterRegionWarp)
        cv::GaussianBlur(grey, smooth, cv::Size(), level.imageSigma, level.imageSigma,
                         cv::BORDER_REPLICATE);
        Painted painted;
        double robustSigma = 1;
        wr = wTrain.clone();
        const cv::Size win(2 * level.window + 1, 2 * level.window + 1);
        for (int it = 0; it < level.iterations; ++it) {
            sampleAt(ux, uy);
            if (it % 4 == 0) {
                const StainFit f = fitStain(grey, idx, ax, ay, wr, tGrid, li.ids.size(),
                                            o.regionGradients, origin);
                painted = painter.paint(f.c0, f.cx, f.cy, f.b, level.imageSigma * s);
                predicted(painted, jw, nullptr, nullptr);
                cv::Mat r0 = smooth - jw;
                removeBias(r0, w, o.biasSigma);
                cv::Mat absR = cv::abs(r0);
                robustSigma = std::max(1e-4, 1.4826 * percentile(absR, 0.5, weight));
            }
            predicted(painted, jw, &gx, &gy);
            r = smooth - jw;
            removeBias(r, w, o.biasSigma);
            // Robust weights: residuals far beyond the typical one (a crack, debris, a
            // region stained unlike the rest of it) weigh little.
            cv::Mat q = r * (1.0 / (o.robustK * robustSigma));
            q = q.mul(q) + 1;
            cv::divide(wTrain, q, wr);
            // Damped Gauss-Newton in local windows: (sum w g g^T + lambda) du = sum w r g.
            cv::Mat wgx = wr.mul(gx), wgy = wr.mul(gy);
            cv::Mat sxx = wgx.mul(gx), sxy = wgx.mul(gy), syy = wgy.mul(gy), sbx = wgx.mul(r),
                    sby = wgy.mul(r);
            cv::Size solveSize = gs;
            if (o.nodeGrid) {
                // A coarse control grid (spacing 2 x window): each node sums the evidence of its
                // cell and its neighbours' (tent-like), so every node sees many boundaries of
                // many orientations and the field has few degrees of freedom.
                solveSize = cv::Size(std::max(2, cvRound(gs.width / (2.0 * level.window))),
                                     std::max(2, cvRound(gs.height / (2.0 * level.window))));
                for (cv::Mat* m : {&sxx, &sxy, &syy, &sbx, &sby}) {
                    cv::resize(*m, *m, solveSize, 0, 0, cv::INTER_AREA);
                    cv::GaussianBlur(*m, *m, cv::Size(3, 3), 0.8, 0.8, cv::BORDER_REPLICATE);
                }
                pxx = sxx;
                pxy = sxy;
                pyy = syy;
                bx = sbx;
                by = sby;
            } else {
                cv::blur(sxx, pxx, win, cv::Point(-1, -1), cv::BORDER_REPLICATE);
                cv::blur(sxy, pxy, win, cv::Point(-1, -1), cv::BORDER_REPLICATE);
                cv::blur(syy, pyy, win, cv::Point(-1, -1), cv::BORDER_REPLICATE);
                cv::blur(sbx, bx, win, cv::Point(-1, -1), cv::BORDER_REPLICATE);
                cv::blur(sby, by, win, cv::Point(-1, -1), cv::BORDER_REPLICATE);
            }
            const double energy =
                cv::mean(pxx + pyy)[0] / 2 * cv::sum(w)[0] / std::max(1.0, cv::sum(wTrain)[0]);
            // The damping is the prior of a MAP step: noise of variance sigma^2 (the robust
            // residual), correlated over 4 pi s^2 px by the smoothing, averaged over a window
            // (or control cell) of n px, against a prior of priorAtlasPx on the displacement.
            // Weak evidence (low contrast, heavy texture) then moves little.
            const double n =
                o.nodeGrid ? 2.0 * (2.0 * level.window) * (2.0 * level.window) : double(win.area());
            const double corr = std::max(1.0, 4 * CV_PI * level.imageSigma * level.imageSigma);
            const double prior =
                corr * robustSigma * robustSigma / (n * o.priorAtlasPx * o.priorAtlasPx);
            const float lambda = float(std::max({1e-12, o.damping * energy, prior}));
            dux.create(solveSize, CV_32F);
            duy.create(solveSize, CV_32F);
            const float maxStep = float(o.maxStepGridPx * s);
            for (int y = 0; y < solveSize.height; ++y) {
                const float* a = pxx.ptr<float>(y);
                const float* b = pxy.ptr<float>(y);
                const float* c = pyy.ptr<float>(y);
                const float* ex = bx.ptr<float>(y);
                const float* ey = by.ptr<float>(y);
                float* ox = dux.ptr<float>(y);
                float* oy = duy.ptr<float>(y);
                for (int x = 0; x < solveSize.width; ++x) {
                    const float aa = a[x] + lambda, cc = c[x] + lambda;
                    const float d = aa * cc - b[x] * b[x];
                    float vx = (cc * ex[x] - b[x] * ey[x]) / d;
                    float vy = (aa * ey[x] - b[x] * ex[x]) / d;
                    const float len = std::sqrt(vx * vx + vy * vy);
                    if (len > maxStep) {
                        vx *= maxStep / len;
                        vy *= maxStep / len;
                    }
                    ox[x] = vx;
                    oy[x] = vy;
                }
            }
            if (solveSize != gs) {
                cv::resize(dux, dux, gs, 0, 0, cv::INTER_LINEAR);
                cv::resize(duy, duy, gs, 0, 0, cv::INTER_LINEAR);
            }
            // Every step must lower the robust (Cauchy) energy whose weights the step used.
            const double c = o.robustK * robustSigma;
            auto cauchy = [&](const cv::Mat& res) {
                cv::Mat e = res * (1.0 / c);
                e = e.mul(e) + 1;
                cv::log(e, e);
                return weightedMean(e, wTrain);
            };
            const double energyNow = cauchy(r);
            auto robustEnergy = [&](const cv::Mat& cx, const cv::Mat& cy) {
                sampleAt(cx, cy);
                cv::Mat jn;
                predicted(painted, jn, nullptr, nullptr);
                cv::Mat rn = smooth - jn;
                removeBias(rn, w, o.biasSigma);
                return cauchy(rn);
            };
            // Regularise: the accumulated field is smoothed after every step; a step that would
            // fold the map (or shrink it locally below minJacobian) is halved.
            bool taken = false;
            for (int half = 0; half < 4 && !taken; ++half) {
                if (o.fieldSigma > 0) {
                    cv::GaussianBlur(dux, cand1, cv::Size(), o.fieldSigma, o.fieldSigma,
                                     cv::BORDER_REPLICATE);
                    cv::GaussianBlur(duy, cand2, cv::Size(), o.fieldSigma, o.fieldSigma,
                                     cv::BORDER_REPLICATE);
                    cand1 += ux;
                    cand2 += uy;
                } else {
                    cand1 = ux + dux;
                    cand2 = uy + duy;
                }
                if (o.elasticSigma > 0) {
                    cv::GaussianBlur(cand1, cand1, cv::Size(), o.elasticSigma, o.elasticSigma,
                                     cv::BORDER_REPLICATE);
                    cv::GaussianBlur(cand2, cand2, cv::Size(), o.elasticSigma, o.elasticSigma,
                                     cv::BORDER_REPLICATE);
                }
                const double m = minRelative(jacobianDet(mapX + cand1, mapY + cand2), refDet);
                if (m >= std::min(o.minJacobian, minRel) - 1e-4 &&
                    robustEnergy(cand1, cand2) < energyNow) {
                    ux = cand1.clone();
                    uy = cand2.clone();
                    minRel = m;
                    taken = true;
                    moved = true;
                } else {
                    dux *= 0.5;
                    duy *= 0.5;
                }
            }
        }
    }

    // Without a step the field is the one measured before: its residuals are r2Before.
    const cv::Mat r2After = moved ? residualSq(ux, uy) : r2Before;
    out.explainedAfter = 1 - weightedMean(r2After, wTest) / testVar;
    out.accepted = out.explainedAfter >= out.explainedBefore + o.minGain;
    if (out.accepted) {
        out.ux = ux;
        out.uy = uy;
        out.minJacobian = minRel;
    } else {
        out.minJacobian = minRelative(det0, refDet);
    }

    // Confidence: the local share of the section's variance the fitted atlas leaves unexplained,
    // halved where the local residual grew, and lowered where the correction was long.
    const cv::Mat& r2 = out.accepted ? r2After : r2Before;
    const int cw = 2 * finest.window + 1;
    cv::Mat lw, la, lb;
    cv::blur(w, lw, cv::Size(cw, cw), cv::Point(-1, -1), cv::BORDER_REPLICATE);
    cv::blur(w.mul(r2), la, cv::Size(cw, cw), cv::Point(-1, -1), cv::BORDER_REPLICATE);
    cv::blur(w.mul(r2Before), lb, cv::Size(cw, cw), cv::Point(-1, -1), cv::BORDER_REPLICATE);
    const float corr = float(o.confidenceCorrectionGridPx * s);
    for (int y = 0; y < gs.height; ++y) {
        const float* ww = w.ptr<float>(y);
        const float* n = lw.ptr<float>(y);
        const float* ra = la.ptr<float>(y);
        const float* rb = lb.ptr<float>(y);
        const float* vx = out.ux.ptr<float>(y);
        const float* vy = out.uy.ptr<float>(y);
        float* c = out.confidence.ptr<float>(y);
        for (int x = 0; x < gs.width; ++x) {
            if (ww[x] <= 0 || n[x] <= 0)
                continue;
            const float after = ra[x] / n[x], before = rb[x] / n[x];
            const float fit = std::clamp(1.0f - after / float(totalVar), 0.0f, 1.0f);
            const float shrink = after <= before || after <= 0 ? 1.0f : before / after;
            const float u2 = (vx[x] * vx[x] + vy[x] * vy[x]) / (corr * corr);
            c[x] = fit * shrink / (1.0f + u2);
        }
    }
    return out;
}

std::vector<std::pair<std::int32_t, double>>
meanByLabel(const cv::Mat& confidence, const cv::Mat& labels, const cv::Mat& valid) {
    CV_Assert(confidence.type() == CV_32F && labels.type() == CV_32S && valid.type() == CV_8U);
    CV_Assert(labels.size() == confidence.size() && valid.size() == confidence.size());
    std::unordered_map<std::int32_t, std::pair<double, double>> acc;
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        const float* c = confidence.ptr<float>(y);
        const uchar* v = valid.ptr<uchar>(y);
        for (int x = 0; x < labels.cols; ++x) {
            if (!v[x] || l[x] == 0)
                continue;
            auto& a = acc[l[x]];
            a.first += c[x];
            a.second += 1;
        }
    }
    std::vector<std::pair<std::int32_t, double>> byArea;
    for (const auto& [id, a] : acc)
        byArea.emplace_back(id, a.second);
    std::sort(byArea.begin(), byArea.end(), [](const auto& p, const auto& q) {
        return p.second != q.second ? p.second > q.second : p.first < q.first;
    });
    for (auto& [id, value] : byArea)
        value = acc[id].first / acc[id].second;
    return byArea;
}

} // namespace slicestation::pipeline
