#include "slicestation/pipeline/intensity_affine.hpp"

#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "stage_measures.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>

namespace slicestation::pipeline {
namespace {

constexpr int kGainTerms = 6; // 1, x, y, x^2, xy, y^2: vignetting and illumination gradients
constexpr int kBiasTerms = 3; // 1, x, y: glass level and its gradient
constexpr int kTerms = kGainTerms + kBiasTerms;

/// Grid coordinates normalised about the measured area's centre: x' = (x - cx) / r. Affine
/// updates are expressed in them so that the six parameters are equally conditioned.
struct Frame {
    double cx = 0, cy = 0, r = 1;
    cv::Matx33d normalised() const { return {1 / r, 0, -cx / r, 0, 1 / r, -cy / r, 0, 0, 1}; }
};

/// The intensity model's terms at one pixel: gain basis then bias basis.
std::array<double, kTerms> basis(double u, double v) {
    return {1, u, v, u * u, u * v, v * v, 1, u, v};
}

/// The plane, smoothed, and its gradient per atlas px.
struct Plane {
    cv::Mat t, tx, ty;
};

Plane smoothedPlane(const cv::Mat& intensity, double sigmaAtlasPx) {
    Plane p;
    if (sigmaAtlasPx > 0.3)
        cv::GaussianBlur(intensity, p.t, cv::Size(), sigmaAtlasPx, sigmaAtlasPx,
                         cv::BORDER_REPLICATE);
    else
        p.t = intensity;
    cv::Sobel(p.t, p.tx, CV_32F, 1, 0, 1, 0.5, 0, cv::BORDER_REPLICATE);
    cv::Sobel(p.t, p.ty, CV_32F, 0, 1, 1, 0.5, 0, cv::BORDER_REPLICATE);
    return p;
}

class Fitter {
public:
    Fitter(const cv::Mat& weight, const Frame& frame) : frame_(frame), size_(weight.size()) {
        mx_.create(size_, CV_32F);
        my_.create(size_, CV_32F);
    }

    /// The plane (and, when asked, its gradient) seen through `a` at every grid pixel.
    void sample(const Plane& p, const cv::Matx23d& a, bool gradient) {
        for (int y = 0; y < size_.height; ++y) {
            float* ox = mx_.ptr<float>(y);
            float* oy = my_.ptr<float>(y);
            for (int x = 0; x < size_.width; ++x) {
                ox[x] = float(a(0, 0) * x + a(0, 1) * y + a(0, 2));
                oy[x] = float(a(1, 0) * x + a(1, 1) * y + a(1, 2));
            }
        }
        // Outside the plane the template is the glass (0).
        cv::remap(p.t, tv_, mx_, my_, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
        if (gradient) {
            cv::remap(p.tx, gx_, mx_, my_, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
            cv::remap(p.ty, gy_, mx_, my_, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
        }
    }

    /// Weighted least squares of the model's coefficients on the last sample.
    std::array<double, kTerms> fit(const cv::Mat& g, const cv::Mat& w) const {
        cv::Matx<double, kTerms, kTerms> n = cv::Matx<double, kTerms, kTerms>::zeros();
        cv::Matx<double, kTerms, 1> b = cv::Matx<double, kTerms, 1>::zeros();
        for (int y = 0; y < size_.height; ++y) {
            const float* gg = g.ptr<float>(y);
            const float* ww = w.ptr<float>(y);
            const float* tt = tv_.ptr<float>(y);
            for (int x = 0; x < size_.width; ++x) {
                if (ww[x] <= 0)
                    continue;
                std::array<double, kTerms> a = term(x, y);
                for (int k = 0; k < kGainTerms; ++k)
                    a[size_t(k)] *= tt[x];
                for (int r = 0; r < kTerms; ++r) {
                    b(r) += ww[x] * gg[x] * a[size_t(r)];
                    for (int c = r; c < kTerms; ++c)
                        n(r, c) += ww[x] * a[size_t(r)] * a[size_t(c)];
                }
            }
        }
        double trace = 0;
        for (int r = 0; r < kTerms; ++r) {
            for (int c = 0; c < r; ++c)
                n(r, c) = n(c, r);
            trace += n(r, r);
        }
        for (int r = 0; r < kTerms; ++r)
            n(r, r) += 1e-6 * trace / kTerms + 1e-12; // a faint ridge: a narrow measured area
        cv::Matx<double, kTerms, 1> sol;
        std::array<double, kTerms> out{};
        if (cv::solve(n, b, sol, cv::DECOMP_CHOLESKY))
            for (int k = 0; k < kTerms; ++k)
                out[size_t(k)] = sol(k);
        return out;
    }

    /// Residual g - model and the model's gain, for the last sample.
    void residual(const cv::Mat& g, const std::array<double, kTerms>& c, cv::Mat& r,
                  cv::Mat& gain) const {
        r.create(size_, CV_32F);
        gain.create(size_, CV_32F);
        for (int y = 0; y < size_.height; ++y) {
            const float* gg = g.ptr<float>(y);
            const float* tt = tv_.ptr<float>(y);
            float* rr = r.ptr<float>(y);
            float* ga = gain.ptr<float>(y);
            for (int x = 0; x < size_.width; ++x) {
                const std::array<double, kTerms> a = term(x, y);
                double gn = 0, bias = 0;
                for (int k = 0; k < kGainTerms; ++k)
                    gn += c[size_t(k)] * a[size_t(k)];
                for (int k = kGainTerms; k < kTerms; ++k)
                    bias += c[size_t(k)] * a[size_t(k)];
                ga[x] = float(gn);
                rr[x] = float(gg[x] - gn * tt[x] - bias);
            }
        }
    }

    /// Gauss-Newton normal equations of the six affine updates (atlas px at x', y', 1).
    void normalEquations(const cv::Mat& r, const cv::Mat& gain, const cv::Mat& w, cv::Matx66d& h,
                         cv::Vec6d& e) const {
        h = cv::Matx66d::zeros();
        e = cv::Vec6d::all(0);
        for (int y = 0; y < size_.height; ++y) {
            const float* rr = r.ptr<float>(y);
            const float* ga = gain.ptr<float>(y);
            const float* ww = w.ptr<float>(y);
            const float* tx = gx_.ptr<float>(y);
            const float* ty = gy_.ptr<float>(y);
            const double v = (y - frame_.cy) / frame_.r;
            for (int x = 0; x < size_.width; ++x) {
                if (ww[x] <= 0)
                    continue;
                const double u = (x - frame_.cx) / frame_.r;
                const double jx = ga[x] * tx[x], jy = ga[x] * ty[x];
                const double j[6] = {jx * u, jx * v, jx, jy * u, jy * v, jy};
                for (int a = 0; a < 6; ++a) {
                    e[a] += ww[x] * rr[x] * j[a];
                    for (int b = a; b < 6; ++b)
                        h(a, b) += ww[x] * j[a] * j[b];
                }
            }
        }
        for (int a = 0; a < 6; ++a)
            for (int b = 0; b < a; ++b)
                h(a, b) = h(b, a);
    }

private:
    std::array<double, kTerms> term(int x, int y) const {
        return basis((x - frame_.cx) / frame_.r, (y - frame_.cy) / frame_.r);
    }

    Frame frame_;
    cv::Size size_;
    cv::Mat mx_, my_, tv_, gx_, gy_;
};

/// Mean Cauchy energy of residuals `r` at scale `c` under weights `w`.
double cauchyEnergy(const cv::Mat& r, double c, const cv::Mat& w) {
    cv::Mat e = r * (1.0 / c);
    e = e.mul(e) + 1;
    cv::log(e, e);
    return weightedMean(e, w);
}

} // namespace

IntensityAffine refineAffineByIntensity(const cv::Mat& grey, const cv::Mat& weight,
                                        const cv::Matx23d& atlasFromGrid,
                                        const cv::Mat& atlasIntensity,
                                        const IntensityAffineOptions& o) {
    CV_Assert(grey.type() == CV_32F && weight.type() == CV_8U && weight.size() == grey.size());
    CV_Assert(atlasIntensity.type() == CV_32F && !atlasIntensity.empty());
    IntensityAffine out;
    out.atlasFromGrid = atlasFromGrid;
    if (cv::countNonZero(weight) < 64 || o.levelSigmas.empty())
        return out;
    const cv::Size gs = grey.size();
    cv::Mat w;
    weight.convertTo(w, CV_32F, 1.0 / 255);
    cv::threshold(w, w, 0, 1, cv::THRESH_BINARY);
    const HeldOutWeights held = heldOutWeights(w, o.holdOutBlockPx);
    const cv::Mat &wTrain = held.train, &wTest = held.test; // named: lambdas capture them
    const cv::Moments m = cv::moments(weight != 0, true);
    Frame frame;
    frame.cx = m.m10 / m.m00;
    frame.cy = m.m01 / m.m00;
    frame.r = 0.5 * std::max(gs.width, gs.height);
    const double s = std::sqrt(std::abs(det(atlasFromGrid))); // atlas px per grid px
    if (!(s > 0))
        return out;
    // The measured area's corners bound how far a step moves any point.
    const cv::Rect box = cv::boundingRect(weight != 0);
    const std::array<cv::Point2d, 4> corners{
        cv::Point2d((box.x - frame.cx) / frame.r, (box.y - frame.cy) / frame.r),
        cv::Point2d((box.br().x - frame.cx) / frame.r, (box.y - frame.cy) / frame.r),
        cv::Point2d((box.x - frame.cx) / frame.r, (box.br().y - frame.cy) / frame.r),
        cv::Point2d((box.br().x - frame.cx) / frame.r, (box.br().y - frame.cy) / frame.r)};

    Fitter fitter(weight, frame);
    cv::Mat smooth, r, gain;
    // Held-out explained share at the finest level: the model fitted on the training blocks,
    // judged on the others.
    const double finest = o.levelSigmas.back();
    cv::Mat finestGrey;
    cv::GaussianBlur(grey, finestGrey, cv::Size(), finest, finest, cv::BORDER_REPLICATE);
    const Plane finestPlane = smoothedPlane(atlasIntensity, finest * s);
    const double testMean = weightedMean(finestGrey, wTest);
    cv::Mat centred = finestGrey - testMean;
    const double testVar = std::max(1e-12, weightedMean(centred.mul(centred), wTest));
    auto explained = [&](const cv::Matx23d& a) {
        fitter.sample(finestPlane, a, false);
        fitter.residual(finestGrey, fitter.fit(finestGrey, wTrain), r, gain);
        return 1 - weightedMean(r.mul(r), wTest) / testVar;
    };
    out.explainedBefore = explained(atlasFromGrid);

    cv::Matx23d a = atlasFromGrid;
    const cv::Matx33d toNormalised = frame.normalised();
    cv::Mat wr;
    for (const double sigma : o.levelSigmas) {
        cv::GaussianBlur(grey, smooth, cv::Size(), sigma, sigma, cv::BORDER_REPLICATE);
        const Plane plane = smoothedPlane(atlasIntensity, sigma * s);
        double robustSigma = 0;
        wr = wTrain.clone();
        for (int it = 0; it < o.iterations; ++it) {
            fitter.sample(plane, a, true);
            const auto coef = fitter.fit(smooth, wr);
            fitter.residual(smooth, coef, r, gain);
            if (it == 0) {
                cv::Mat absR = cv::abs(r);
                robustSigma = std::max(1e-5, 1.4826 * double(percentile(absR, 0.5, wTrain > 0)));
            }
            const double c = o.robustK * robustSigma;
            cv::Mat q = r * (1.0 / c);
            q = q.mul(q) + 1;
            cv::divide(wTrain, q, wr);
            cv::Matx66d h;
            cv::Vec6d e;
            fitter.normalEquations(r, gain, wr, h, e);
            double trace = 0;
            for (int k = 0; k < 6; ++k)
                trace += h(k, k);
            if (!(trace > 0))
                break;
            for (int k = 0; k < 6; ++k)
                h(k, k) += o.damping * trace / 6;
            cv::Vec6d d;
            if (!cv::solve(h, e, d, cv::DECOMP_CHOLESKY))
                break;
            double longest = 0;
            for (const cv::Point2d& p : corners)
                longest = std::max(longest, std::hypot(d[0] * p.x + d[1] * p.y + d[2],
                                                       d[3] * p.x + d[4] * p.y + d[5]));
            const double maxMove = o.maxStepGridPx * s;
            if (longest > maxMove) {
                d *= maxMove / longest;
                longest = maxMove;
            }
            const double energyNow = cauchyEnergy(r, c, wTrain);
            bool taken = false;
            for (int half = 0; half < 4 && !taken; ++half) {
                // a' = a + D N: the update is an affine of the normalised coordinates.
                const cv::Matx23d dn(d[0], d[1], d[2], d[3], d[4], d[5]);
                const cv::Matx33d dN = cv::Matx33d(dn(0, 0), dn(0, 1), dn(0, 2), dn(1, 0), dn(1, 1),
                                                   dn(1, 2), 0, 0, 0) *
                                       toNormalised;
                cv::Matx23d cand = a;
                for (int i = 0; i < 2; ++i)
                    for (int j = 0; j < 3; ++j)
                        cand(i, j) += dN(i, j);
                fitter.sample(plane, cand, false);
                cv::Mat rc, gc;
                fitter.residual(smooth, coef, rc, gc);
                if (cauchyEnergy(rc, c, wTrain) < energyNow) {
                    a = cand;
                    taken = true;
                    ++out.steps;
                } else {
                    d *= 0.5;
                    longest *= 0.5;
                }
            }
            if (!taken || longest < 0.01 * s)
                break;
        }
    }
    out.explainedAfter = explained(a);
    out.planeIsTheStain = out.explainedAfter >= o.minExplained;
    out.accepted = out.explainedAfter >= out.explainedBefore + o.minGain && out.planeIsTheStain;
    if (out.accepted)
        out.atlasFromGrid = a;
    return out;
}

} // namespace slicestation::pipeline
