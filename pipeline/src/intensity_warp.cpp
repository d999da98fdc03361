#include "slicestation/pipeline/intensity_warp.hpp"

#include "slicestation/pipeline/mask_ops.hpp"
#include "stage_measures.hpp"

#include <Eigen/Cholesky>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

namespace slicestation::pipeline {
namespace {

constexpr int kGainTerms = 6; // 1, x, y, x^2, xy, y^2
constexpr int kBiasTerms = 3; // 1, x, y
constexpr int kTerms = kGainTerms + kBiasTerms;

/// Smallest `det` / `ref` inside the grid (the outermost pixels' one-sided differences are
/// halved by the replicated border and are left out).
double minRelative(const cv::Mat& det, double ref) {
    double lo = 0, hi = 0;
    const cv::Mat inner =
        det.rows > 2 && det.cols > 2 ? det(cv::Rect(1, 1, det.cols - 2, det.rows - 2)) : det;
    cv::minMaxLoc(inner, &lo, &hi);
    return ref > 0 ? lo / ref : hi / ref;
}

/// Whether the map's Jacobian determinant `det` stays regular against the start's `det0` (both
/// relative to `ref`), inside the grid: at least `floor` where the start was, and where the
/// start was already below it (a fold the earlier stages left) no more than `slack` below the
/// start, so that a fold elsewhere neither blocks every step nor may deepen freely.
bool regular(const cv::Mat& det, const cv::Mat& det0, double ref, double floor, double slack) {
    for (int y = 1; y + 1 < det.rows; ++y) {
        const float* d = det.ptr<float>(y);
        const float* d0 = det0.ptr<float>(y);
        for (int x = 1; x + 1 < det.cols; ++x) {
            const double a = d[x] / ref, a0 = d0[x] / ref;
            const double bound = a0 >= floor ? floor : a0 - slack;
            if (a < bound - 1e-4)
                return false;
        }
    }
    return true;
}

/// The intensity model gain x T + bias, fitted by weighted least squares: global polynomials
/// (the intensity affine's model) or a local linear regression in a Gaussian window.
class Model {
public:
    Model(cv::Size size, double localSigma) : size_(size), localSigma_(localSigma) {
        const double cx = 0.5 * (size.width - 1), cy = 0.5 * (size.height - 1);
        const double r = 0.5 * std::max(size.width, size.height);
        for (int k = 0; k < kTerms; ++k)
            basis_[size_t(k)].create(size, CV_32F);
        for (int y = 0; y < size.height; ++y)
            for (int x = 0; x < size.width; ++x) {
                const float u = float((x - cx) / r), v = float((y - cy) / r);
                const float b[kTerms] = {1, u, v, u * u, u * v, v * v, 1, u, v};
                for (int k = 0; k < kTerms; ++k)
                    basis_[size_t(k)].at<float>(y, x) = b[k];
            }
    }

    /// Fits the model to `g` ~ model(`t`) under weights `w`; writes the residual (everywhere)
    /// and the gain.
    void fit(const cv::Mat& g, const cv::Mat& t, const cv::Mat& w, cv::Mat& r, cv::Mat& gain) {
        if (localSigma_ > 0)
            fitLocal(g, t, w, r, gain);
        else
            fitGlobal(g, t, w, r, gain);
    }

private:
    void fitGlobal(const cv::Mat& g, const cv::Mat& t, const cv::Mat& w, cv::Mat& r,
                   cv::Mat& gain) {
        cv::Matx<double, kTerms, kTerms> n = cv::Matx<double, kTerms, kTerms>::zeros();
        cv::Matx<double, kTerms, 1> b = cv::Matx<double, kTerms, 1>::zeros();
        for (int y = 0; y < size_.height; ++y) {
            const float* gg = g.ptr<float>(y);
            const float* ww = w.ptr<float>(y);
            const float* tt = t.ptr<float>(y);
            for (int x = 0; x < size_.width; ++x) {
                if (ww[x] <= 0)
                    continue;
                double a[kTerms];
                for (int k = 0; k < kTerms; ++k)
                    a[k] = basis_[size_t(k)].ptr<float>(y)[x] * (k < kGainTerms ? tt[x] : 1.0f);
                for (int i = 0; i < kTerms; ++i) {
                    b(i) += ww[x] * gg[x] * a[i];
                    for (int j = i; j < kTerms; ++j)
                        n(i, j) += ww[x] * a[i] * a[j];
                }
            }
        }
        double trace = 0;
        for (int i = 0; i < kTerms; ++i) {
            for (int j = 0; j < i; ++j)
                n(i, j) = n(j, i);
            trace += n(i, i);
        }
        for (int i = 0; i < kTerms; ++i)
            n(i, i) += 1e-6 * trace / kTerms + 1e-12;
        cv::Matx<double, kTerms, 1> c = cv::Matx<double, kTerms, 1>::zeros();
        if (!cv::solve(n, b, c, cv::DECOMP_CHOLESKY))
            c = cv::Matx<double, kTerms, 1>::zeros();
        gain = cv::Mat::zeros(size_, CV_32F);
        cv::Mat bias = cv::Mat::zeros(size_, CV_32F);
        for (int k = 0; k < kGainTerms; ++k)
            cv::scaleAdd(basis_[size_t(k)], c(k), gain, gain);
        for (int k = kGainTerms; k < kTerms; ++k)
            cv::scaleAdd(basis_[size_t(k)], c(k), bias, bias);
        r = g - gain.mul(t) - bias;
    }

    void fitLocal(const cv::Mat& g, const cv::Mat& t, const cv::Mat& w, cv::Mat& r, cv::Mat& gain) {
        const double s = localSigma_;
        // A wide window's moments are smooth: blurred on a copy reduced 4 times (when the
        // window is at least 8 px) and brought back bilinearly, a tenth of the full blur's cost.
        const int f = s >= 8 ? 4 : 1;
        const cv::Size small((size_.width + f - 1) / f, (size_.height + f - 1) / f);
        auto blur = [s, f, small, this](const cv::Mat& in) {
            cv::Mat out;
            if (f == 1) {
                cv::GaussianBlur(in, out, cv::Size(), s, s, cv::BORDER_REPLICATE);
                return out;
            }
            cv::resize(in, out, small, 0, 0, cv::INTER_AREA);
            cv::GaussianBlur(out, out, cv::Size(), s / f, s / f, cv::BORDER_REPLICATE);
            cv::resize(out, out, size_, 0, 0, cv::INTER_LINEAR);
            return out;
        };
        const cv::Mat wt = w.mul(t), wg = w.mul(g);
        cv::Mat sw = blur(w), st = blur(wt), sg = blur(wg), stt = blur(wt.mul(t)),
                stg = blur(wt.mul(g));
        sw = cv::max(sw, 1e-6);
        const cv::Mat mt = st / sw, mg = sg / sw;
        cv::Mat vt = stt / sw - mt.mul(mt), cov = stg / sw - mt.mul(mg);
        // A floor on the plane's local variance: where the plane is flat the model falls back
        // to the local mean instead of an unbounded gain.
        cv::Mat tc = t - weightedMean(t, w);
        const double floor = 0.01 * weightedMean(tc.mul(tc), w) + 1e-12;
        vt = cv::max(vt, 0) + floor;
        gain = cov / vt;
        const cv::Mat bias = mg - gain.mul(mt);
        r = g - gain.mul(t) - bias;
    }

    cv::Size size_;
    double localSigma_;
    std::array<cv::Mat, kTerms> basis_;
};

/// Cubic B-spline basis on a control grid of spacing h: control i sits at (i - 1) h.
struct Axis {
    std::vector<int> first;                  ///< first active control per pixel
    std::vector<std::array<float, 4>> basis; ///< its four weights
    int controls = 0;
};

Axis makeAxis(int pixels, double h, double origin) {
    // The lattice starts at or before pixel 0.
    origin -= h * std::ceil(origin / h);
    Axis a;
    a.first.resize(size_t(pixels));
    a.basis.resize(size_t(pixels));
    for (int x = 0; x < pixels; ++x) {
        const double t = (x - origin) / h;
        const int i = static_cast<int>(std::floor(t));
        const double f = t - i, g = 1 - f;
        a.first[size_t(x)] = i;
        a.basis[size_t(x)] = {float(g * g * g / 6), float((3 * f * f * f - 6 * f * f + 4) / 6),
                              float((-3 * f * f * f + 3 * f * f + 3 * f + 1) / 6),
                              float(f * f * f / 6)};
    }
    a.controls = static_cast<int>(std::floor((pixels - 1 - origin) / h)) + 4;
    return a;
}

/// The dense field of control displacements `c` (ny x nx, CV_64F).
cv::Mat evaluate(const Axis& ax, const Axis& ay, const cv::Mat& c) {
    // Separable: first along x for every control row, then along y.
    cv::Mat rows(c.rows, int(ax.first.size()), CV_32F);
    for (int j = 0; j < c.rows; ++j) {
        const double* cr = c.ptr<double>(j);
        float* out = rows.ptr<float>(j);
        for (size_t x = 0; x < ax.first.size(); ++x) {
            const int i = ax.first[x];
            const auto& b = ax.basis[x];
            out[x] = float(b[0] * cr[i] + b[1] * cr[i + 1] + b[2] * cr[i + 2] + b[3] * cr[i + 3]);
        }
    }
    cv::Mat u(int(ay.first.size()), rows.cols, CV_32F);
    for (size_t y = 0; y < ay.first.size(); ++y) {
        const int j = ay.first[y];
        const auto& b = ay.basis[y];
        float* out = u.ptr<float>(int(y));
        const float* r0 = rows.ptr<float>(j);
        const float* r1 = rows.ptr<float>(j + 1);
        const float* r2 = rows.ptr<float>(j + 2);
        const float* r3 = rows.ptr<float>(j + 3);
        for (int x = 0; x < u.cols; ++x)
            out[x] = b[0] * r0[x] + b[1] * r1[x] + b[2] * r2[x] + b[3] * r3[x];
    }
    return u;
}

/// Gauss-Newton normal equations of the control displacements (x block then y block, control k
/// = j nx + i): H = sum w J^T J, e = sum w r J with J = gain (Tx, Ty) B_k. Accumulated
/// separably: per image row, products of the x basis, then spread over the rows' y basis.
void normalEquations(const Axis& ax, const Axis& ay, const cv::Mat& wr, const cv::Mat& r,
                     const cv::Mat& jx, const cv::Mat& jy, cv::Mat& h, cv::Mat& e) {
    const int nx = ax.controls, ny = ay.controls, k = nx * ny;
    h = cv::Mat::zeros(2 * k, 2 * k, CV_64F);
    e = cv::Mat::zeros(2 * k, 1, CV_64F);
    // Row sums, per control column i and offset d (0..3): xx, xy, yy products; and e parts.
    std::vector<double> rxx(size_t(nx) * 4, 0.0), rxy(size_t(nx) * 4, 0.0),
        ryy(size_t(nx) * 4, 0.0), ex(size_t(nx), 0.0), ey(size_t(nx), 0.0);
    for (size_t y = 0; y < ay.first.size(); ++y) {
        std::fill(rxx.begin(), rxx.end(), 0.0);
        std::fill(rxy.begin(), rxy.end(), 0.0);
        std::fill(ryy.begin(), ryy.end(), 0.0);
        std::fill(ex.begin(), ex.end(), 0.0);
        std::fill(ey.begin(), ey.end(), 0.0);
        const float* ww = wr.ptr<float>(int(y));
        const float* rr = r.ptr<float>(int(y));
        const float* gx = jx.ptr<float>(int(y));
        const float* gy = jy.ptr<float>(int(y));
        bool any = false;
        for (size_t x = 0; x < ax.first.size(); ++x) {
            if (ww[x] <= 0)
                continue;
            any = true;
            const double a = ww[x] * gx[x] * gx[x], b = ww[x] * gx[x] * gy[x],
                         c = ww[x] * gy[x] * gy[x], px = ww[x] * rr[x] * gx[x],
                         py = ww[x] * rr[x] * gy[x];
            const int i = ax.first[x];
            const auto& bs = ax.basis[x];
            for (int p = 0; p < 4; ++p) {
                ex[size_t(i + p)] += px * bs[size_t(p)];
                ey[size_t(i + p)] += py * bs[size_t(p)];
                for (int q = p; q < 4; ++q) {
                    const double v = double(bs[size_t(p)]) * bs[size_t(q)];
                    const size_t at = size_t(i + p) * 4 + size_t(q - p);
                    rxx[at] += a * v;
                    rxy[at] += b * v;
                    ryy[at] += c * v;
                }
            }
        }
        if (!any)
            continue;
        const int j0 = ay.first[y];
        const auto& by = ay.basis[y];
        for (int p = 0; p < 4; ++p) {
            for (int i = 0; i < nx; ++i) {
                const int kk = (j0 + p) * nx + i;
                e.at<double>(kk) += by[size_t(p)] * ex[size_t(i)];
                e.at<double>(k + kk) += by[size_t(p)] * ey[size_t(i)];
            }
            for (int q = 0; q < 4; ++q) {
                const double v = double(by[size_t(p)]) * by[size_t(q)];
                for (int i = 0; i < nx; ++i)
                    for (int d = 0; d < 4 && i + d < nx; ++d) {
                        const size_t at = size_t(i) * 4 + size_t(d);
                        if (rxx[at] == 0 && rxy[at] == 0 && ryy[at] == 0)
                            continue;
                        const int kk = (j0 + p) * nx + i, ll = (j0 + q) * nx + i + d;
                        const double vxx = v * rxx[at], vxy = v * rxy[at], vyy = v * ryy[at];
                        h.at<double>(kk, ll) += vxx;
                        h.at<double>(k + kk, k + ll) += vyy;
                        h.at<double>(kk, k + ll) += vxy;
                        h.at<double>(k + kk, ll) += vxy;
                        if (d > 0) {
                            h.at<double>(ll, kk) += vxx;
                            h.at<double>(k + ll, k + kk) += vyy;
                            h.at<double>(ll, k + kk) += vxy;
                            h.at<double>(k + ll, kk) += vxy;
                        }
                    }
            }
        }
    }
}

/// Graph Laplacian of the control grid (4-neighbours), both components: sum over neighbour
/// pairs of |c_k - c_l|^2 = c^T L c.
cv::Mat membrane(int nx, int ny) {
    const int k = nx * ny;
    cv::Mat l = cv::Mat::zeros(2 * k, 2 * k, CV_64F);
    auto link = [&](int a, int b) {
        for (int o : {0, k}) {
            l.at<double>(o + a, o + a) += 1;
            l.at<double>(o + b, o + b) += 1;
            l.at<double>(o + a, o + b) -= 1;
            l.at<double>(o + b, o + a) -= 1;
        }
    };
    for (int j = 0; j < ny; ++j)
        for (int i = 0; i < nx; ++i) {
            if (i + 1 < nx)
                link(j * nx + i, j * nx + i + 1);
            if (j + 1 < ny)
                link(j * nx + i, (j + 1) * nx + i);
        }
    return l;
}

/// L c for the membrane's L (both components) without the dense product: (L c)_a is the sum,
/// over the 4-neighbours b of control a, of c_a - c_b.
cv::Mat membraneTimes(int nx, int ny, const cv::Mat& c) {
    const int k = nx * ny;
    cv::Mat out(2 * k, 1, CV_64F);
    for (int o : {0, k})
        for (int j = 0; j < ny; ++j)
            for (int i = 0; i < nx; ++i) {
                const int a = j * nx + i;
                const double ca = c.at<double>(o + a);
                double sum = 0;
                if (j > 0)
                    sum += ca - c.at<double>(o + a - nx);
                if (i > 0)
                    sum += ca - c.at<double>(o + a - 1);
                if (i + 1 < nx)
                    sum += ca - c.at<double>(o + a + 1);
                if (j + 1 < ny)
                    sum += ca - c.at<double>(o + a + nx);
                out.at<double>(o + a) = sum;
            }
    return out;
}

/// Solves a d = rhs for a symmetric positive definite `a` (CV_64F, continuous) with Eigen's
/// blocked Cholesky: through cv::solve, Debian's reference BLAS took most of the stage's time.
/// False when `a` is not positive definite.
bool solvePositiveDefinite(const cv::Mat& a, const cv::Mat& rhs, cv::Mat& d) {
    using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
    CV_Assert(a.type() == CV_64F && a.isContinuous() && rhs.type() == CV_64F &&
              rhs.isContinuous() && rhs.rows == a.rows && rhs.cols == 1);
    const Eigen::LLT<RowMajor> llt(Eigen::Map<const RowMajor>(a.ptr<double>(), a.rows, a.cols));
    if (llt.info() != Eigen::Success)
        return false;
    d.create(rhs.rows, 1, CV_64F);
    Eigen::Map<Eigen::VectorXd>(d.ptr<double>(), d.rows) =
        llt.solve(Eigen::Map<const Eigen::VectorXd>(rhs.ptr<double>(), rhs.rows));
    return true;
}

/// Mean Cauchy energy of residuals `r` at scale `c` under weights `w`, times c^2 / 2 (so that
/// its Gauss-Newton model has the IRLS weights 1 / (1 + (r/c)^2)); summed, not averaged.
double cauchySum(const cv::Mat& r, double c, const cv::Mat& w) {
    cv::Mat e = r * (1.0 / c);
    e = e.mul(e) + 1;
    cv::log(e, e);
    return 0.5 * c * c * e.dot(w);
}

} // namespace

IntensityWarp refineWarpByIntensity(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                                    const cv::Mat& mapY, const cv::Mat& atlasIntensity,
                                    const IntensityWarpOptions& o) {
    CV_Assert(grey.type() == CV_32F && weight.type() == CV_8U && weight.size() == grey.size());
    CV_Assert(mapX.type() == CV_32F && mapY.type() == CV_32F && mapX.size() == grey.size() &&
              mapY.size() == grey.size());
    CV_Assert(atlasIntensity.type() == CV_32F && !atlasIntensity.empty());
    for (const IntensityWarpLevel& l : o.levels)
        CV_Assert(l.spacingGridPx >= 4 && l.imageSigma >= 0);
    const cv::Size gs = grey.size();
    const cv::Point2d origin = o.origin ? *o.origin : weightCentroid(weight);
    IntensityWarp out;
    out.ux = cv::Mat::zeros(gs, CV_32F);
    out.uy = cv::Mat::zeros(gs, CV_32F);
    const cv::Mat det0 = jacobianDet(mapX, mapY);
    const double refDet = percentile(det0, 0.5, weight);
    out.minJacobian = std::abs(refDet) > 1e-9 ? minRelative(det0, refDet) : 1;
    if (cv::countNonZero(weight) < 64 || o.levels.empty() || !(std::abs(refDet) > 1e-9))
        return out;
    const double s = std::sqrt(std::abs(refDet)); // atlas px per grid px

    cv::Mat w;
    weight.convertTo(w, CV_32F, 1.0 / 255);
    cv::threshold(w, w, 0, 1, cv::THRESH_BINARY);
    const HeldOutWeights held = heldOutWeights(w, o.holdOutBlockPx, origin);
    const cv::Mat &wTrain = held.train, &wTest = held.test; // named: lambdas capture them
    Model model(gs, o.localSigmaGridPx);

    auto smoothed = [](const cv::Mat& m, double sigma) {
        cv::Mat blurred;
        if (sigma > 0.3)
            cv::GaussianBlur(m, blurred, cv::Size(), sigma, sigma, cv::BORDER_REPLICATE);
        else
            blurred = m;
        return blurred;
    };
    cv::Mat ax, ay, tv, r, gain;
    auto sample = [&](const cv::Mat& plane, const cv::Mat& ux, const cv::Mat& uy, cv::Mat& dst) {
        ax = mapX + ux;
        ay = mapY + uy;
        // Outside the plane the template is the glass (0).
        cv::remap(plane, dst, ax, ay, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
    };

    // Held-out explained share at the finest level.
    const double finest = o.levels.back().imageSigma;
    const cv::Mat finestGrey = smoothed(grey, finest);
    const cv::Mat finestPlane = smoothed(atlasIntensity, finest * s);
    const double testMean = weightedMean(finestGrey, wTest);
    cv::Mat centred = finestGrey - testMean;
    const double testVar = std::max(1e-12, weightedMean(centred.mul(centred), wTest));
    auto explained = [&](const cv::Mat& ux, const cv::Mat& uy) {
        sample(finestPlane, ux, uy, tv);
        model.fit(finestGrey, tv, wTrain, r, gain);
        return 1 - weightedMean(r.mul(r), wTest) / testVar;
    };
    out.explainedBefore = explained(out.ux, out.uy);

    cv::Mat baseX = out.ux.clone(), baseY = out.uy.clone(); // the coarser levels' field
    double minRel = out.minJacobian;
    cv::Mat wr, tx, ty, jx, jy, h, e;
    for (const IntensityWarpLevel& level : o.levels) {
        const cv::Mat g = smoothed(grey, level.imageSigma);
        const cv::Mat plane = smoothed(atlasIntensity, level.imageSigma * s);
        cv::Mat px, py;
        cv::Sobel(plane, px, CV_32F, 1, 0, 1, 0.5, 0, cv::BORDER_REPLICATE);
        cv::Sobel(plane, py, CV_32F, 0, 1, 1, 0.5, 0, cv::BORDER_REPLICATE);
        const Axis axX = makeAxis(gs.width, level.spacingGridPx, origin.x);
        const Axis axY = makeAxis(gs.height, level.spacingGridPx, origin.y);
        const int nx = axX.controls, ny = axY.controls, k = nx * ny;
        const cv::Mat lap = membrane(nx, ny);
        cv::Mat c = cv::Mat::zeros(2 * k, 1, CV_64F);
        cv::Mat ux = baseX.clone(), uy = baseY.clone();
        double robustSigma = 0;
        wr = wTrain.clone();
        for (int it = 0; it < level.iterations; ++it) {
            sample(plane, ux, uy, tv);
            model.fit(g, tv, wr, r, gain);
            if (it == 0) {
                cv::Mat absR = cv::abs(r);
                robustSigma = std::max(1e-5, 1.4826 * double(percentile(absR, 0.5, wTrain > 0)));
            }
            const double cs = o.robustK * robustSigma;
            cv::Mat q = r * (1.0 / cs);
            q = q.mul(q) + 1;
            cv::divide(wTrain, q, wr);
            cv::remap(px, tx, ax, ay, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
            cv::remap(py, ty, ax, ay, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
            jx = gain.mul(tx);
            jy = gain.mul(ty);
            normalEquations(axX, axY, wr, r, jx, jy, h, e);
            double diag = 0;
            int seen = 0;
            for (int i = 0; i < 2 * k; ++i)
                if (h.at<double>(i, i) > 0) {
                    diag += h.at<double>(i, i);
                    ++seen;
                }
            if (seen == 0)
                break;
            diag /= seen;
            const double lambda = o.stiffness * diag;
            cv::Mat a = h + lambda * lap;
            a.diag() += o.damping * diag + 1e-12;
            const cv::Mat rhs = e - lambda * membraneTimes(nx, ny, c);
            cv::Mat d;
            if (!solvePositiveDefinite(a, rhs, d))
                break;
            double longest = 0;
            for (int i = 0; i < k; ++i)
                longest = std::max(longest, std::hypot(d.at<double>(i), d.at<double>(k + i)));
            const double maxMove = o.maxStepGridPx * s;
            if (longest > maxMove) {
                d *= maxMove / longest;
                longest = maxMove;
            }
            // Penalised robust energy, with the model's fit held (as in the step's linearisation).
            const cv::Mat fittedGain = gain.clone(), fittedBias = g - r - gain.mul(tv);
            auto energy = [&](const cv::Mat& cc, const cv::Mat& res) {
                return cauchySum(res, cs, wTrain) +
                       0.5 * lambda * cc.dot(membraneTimes(nx, ny, cc));
            };
            const double energyNow = energy(c, r);
            bool taken = false;
            for (int half = 0; half < 4 && !taken; ++half) {
                const cv::Mat cand = c + d;
                const cv::Mat fx = baseX + evaluate(axX, axY, cand.rowRange(0, k).reshape(1, ny));
                const cv::Mat fy =
                    baseY + evaluate(axX, axY, cand.rowRange(k, 2 * k).reshape(1, ny));
                const cv::Mat det = jacobianDet(mapX + fx, mapY + fy);
                const double m = minRelative(det, refDet);
                bool ok = regular(det, det0, refDet, o.minJacobian, o.foldSlack);
                if (ok) {
                    cv::Mat tc;
                    sample(plane, fx, fy, tc);
                    const cv::Mat rc = g - fittedGain.mul(tc) - fittedBias;
                    ok = energy(cand, rc) < energyNow;
                }
                if (ok) {
                    c = cand;
                    ux = fx;
                    uy = fy;
                    minRel = m;
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
        baseX = ux;
        baseY = uy;
    }
    out.explainedAfter = explained(baseX, baseY);
    out.accepted = out.explainedAfter >= out.explainedBefore + o.minGain;
    if (!out.accepted)
        return out;
    out.ux = baseX;
    out.uy = baseY;
    out.minJacobian = minRel;
    if (o.holdOutBlockPx > 0 && o.refitOnAll) {
        // Judged on the held-out blocks, the field kept is fitted on every pixel: the fitting
        // blocks alone are half the data, and which half depends on the checkerboard.
        IntensityWarpOptions all = o;
        all.holdOutBlockPx = 0;
        all.refitOnAll = false;
        all.origin = origin;
        const IntensityWarp refit =
            refineWarpByIntensity(grey, weight, mapX, mapY, atlasIntensity, all);
        if (refit.accepted) {
            out.ux = refit.ux;
            out.uy = refit.uy;
            out.minJacobian = refit.minJacobian;
            out.steps += refit.steps;
        }
    }
    return out;
}

namespace {

/// The labels of `atlasLabels` (CV_32S) seen at every grid pixel under the map (CV_32S).
cv::Mat labelsUnderMap(const cv::Mat& atlasLabels, const cv::Mat& mapX, const cv::Mat& mapY) {
    // remap has no 32S support; labels go through as float bit patterns untouched by NEAREST.
    const cv::Mat asFloat(atlasLabels.size(), CV_32F, atlasLabels.data, atlasLabels.step);
    cv::Mat seenF;
    cv::remap(asFloat, seenF, mapX, mapY, cv::INTER_NEAREST, cv::BORDER_CONSTANT, cv::Scalar(0));
    return cv::Mat(seenF.size(), CV_32S, seenF.data, seenF.step).clone();
}

/// The median of `v` (not empty), reordering it.
float medianInPlace(std::vector<float>& v) {
    std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(v.size() / 2), v.end());
    return v[v.size() / 2];
}

/// paintRegions with the labels each grid pixel sees under the map already looked up (`seen`,
/// labelsUnderMap).
cv::Mat paintSeen(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& seen,
                  const cv::Mat& atlasLabels, const std::vector<std::int32_t>& glassIds,
                  const RegionWarpOptions& o) {
    cv::Mat counts;
    weight.convertTo(counts, CV_32F);
    std::unordered_map<std::int32_t, std::vector<float>> values;
    std::vector<float> tissue;
    for (int y = 0; y < grey.rows; ++y) {
        const float* g = grey.ptr<float>(y);
        const float* w = counts.ptr<float>(y);
        const std::int32_t* l = seen.ptr<std::int32_t>(y);
        for (int x = 0; x < grey.cols; ++x) {
            if (w[x] <= 0)
                continue;
            values[l[x]].push_back(g[x]);
            if (l[x] != 0)
                tissue.push_back(g[x]);
        }
    }
    const float tissueLevel = tissue.empty() ? 1.0f : medianInPlace(tissue);
    const size_t minPx = size_t(std::max(1, o.minRegionPx));
    auto glassIt = values.find(0);
    // Without a glass band the glass is taken as the darkest tenth of what is measured.
    float glassLevel = 0;
    if (glassIt != values.end() && glassIt->second.size() >= minPx) {
        glassLevel = medianInPlace(glassIt->second);
    } else if (!tissue.empty()) {
        std::nth_element(tissue.begin(), tissue.begin() + std::ptrdiff_t(tissue.size() / 10),
                         tissue.end());
        glassLevel = tissue[tissue.size() / 10];
    }
    std::unordered_map<std::int32_t, float> level;
    for (auto& [label, v] : values)
        level[label] = v.size() >= minPx ? medianInPlace(v) : tissueLevel;
    level[0] = glassLevel;
    if (o.glassLike)
        for (std::int32_t id : glassIds)
            level[id] = glassLevel;
    cv::Mat plane(atlasLabels.size(), CV_32F);
    std::int32_t lastLabel = 0;
    float lastLevel = glassLevel;
    for (int y = 0; y < atlasLabels.rows; ++y) {
        const std::int32_t* l = atlasLabels.ptr<std::int32_t>(y);
        float* out = plane.ptr<float>(y);
        for (int x = 0; x < atlasLabels.cols; ++x) {
            if (l[x] != lastLabel) {
                lastLabel = l[x];
                const auto it = level.find(lastLabel);
                lastLevel = it != level.end() ? it->second : tissueLevel;
            }
            out[x] = lastLevel;
        }
    }
    return plane;
}

/// Regions whose grey spreads inside far more than the regions' typical spread (see
/// RegionWarpOptions::maxInnerSpread), under the map.
std::unordered_set<std::int32_t> gradedRegions(const cv::Mat& grey, const cv::Mat& weight,
                                               const cv::Mat& seen, const RegionWarpOptions& o) {
    std::unordered_set<std::int32_t> out;
    if (o.maxInnerSpread <= 0)
        return out;
    constexpr int kInset = 2;
    std::unordered_map<std::int32_t, std::vector<float>> values;
    for (int y = kInset; y + kInset < grey.rows; ++y)
        for (int x = kInset; x + kInset < grey.cols; ++x) {
            const std::int32_t l = seen.at<std::int32_t>(y, x);
            if (l == 0 || weight.at<std::uint8_t>(y, x) == 0)
                continue;
            if (seen.at<std::int32_t>(y - kInset, x) != l ||
                seen.at<std::int32_t>(y + kInset, x) != l ||
                seen.at<std::int32_t>(y, x - kInset) != l ||
                seen.at<std::int32_t>(y, x + kInset) != l)
                continue;
            values[l].push_back(grey.at<float>(y, x));
        }
    std::vector<std::pair<std::int32_t, float>> spreads;
    for (auto& [label, v] : values) {
        if (v.size() < size_t(std::max(1, o.minRegionPx)))
            continue;
        const float m = medianInPlace(v);
        for (float& g : v)
            g = std::abs(g - m);
        spreads.emplace_back(label, medianInPlace(v));
    }
    if (spreads.size() < 3)
        return out;
    std::vector<float> all;
    for (const auto& s : spreads)
        all.push_back(s.second);
    const float typical = medianInPlace(all);
    for (const auto& [label, s] : spreads)
        if (s > o.maxInnerSpread * typical)
            out.insert(label);
    return out;
}

/// `weight` without the grid pixels that see (`seen`, labelsUnderMap) a `left` region.
cv::Mat withoutRegions(const cv::Mat& weight, const cv::Mat& seen,
                       const std::unordered_set<std::int32_t>& left) {
    if (left.empty())
        return weight;
    cv::Mat out = weight.clone();
    for (int y = 0; y < out.rows; ++y) {
        const std::int32_t* l = seen.ptr<std::int32_t>(y);
        std::uint8_t* w = out.ptr<std::uint8_t>(y);
        for (int x = 0; x < out.cols; ++x)
            if (left.count(l[x]))
                w[x] = 0;
    }
    return out;
}

} // namespace

cv::Mat paintRegions(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                     const cv::Mat& mapY, const cv::Mat& atlasLabels,
                     const std::vector<std::int32_t>& glassIds, const RegionWarpOptions& o) {
    CV_Assert(grey.type() == CV_32F && atlasLabels.type() == CV_32S && !atlasLabels.empty());
    CV_Assert(weight.size() == grey.size() && mapX.size() == grey.size() &&
              mapY.size() == grey.size() && mapX.type() == CV_32F && mapY.type() == CV_32F);
    return paintSeen(grey, weight, labelsUnderMap(atlasLabels, mapX, mapY), atlasLabels, glassIds,
                     o);
}

IntensityWarp refineWarpByRegions(const cv::Mat& grey, const cv::Mat& weight, const cv::Mat& mapX,
                                  const cv::Mat& mapY, const cv::Mat& atlasLabels,
                                  const std::vector<std::int32_t>& glassIds,
                                  const RegionWarpOptions& o) {
    CV_Assert(atlasLabels.type() == CV_32S && !atlasLabels.empty());
    CV_Assert(!o.warp.levels.empty());
    const cv::Size gs = grey.size();
    // One lattice and checkerboard for every fit below (the weights they get differ).
    IntensityWarpOptions warp = o.warp;
    if (!warp.origin)
        warp.origin = weightCentroid(weight);
    warp.refitOnAll = false; // the levels are judged and fitted again together, below
    // The regions' levels come from the fitting blocks only, so that the held-out check below
    // judges each map on pixels its painting did not see.
    cv::Mat paintWeight = weight.clone();
    if (o.warp.holdOutBlockPx > 0)
        for (int y = 0; y < gs.height; ++y) {
            std::uint8_t* p = paintWeight.ptr<std::uint8_t>(y);
            for (int x = 0; x < gs.width; ++x)
                if (heldOutBlock(x, y, o.warp.holdOutBlockPx, *warp.origin))
                    p[x] = 0;
        }
    // The held-out explained share of a map against its own painting, at the finest level (the
    // judgement `fit` below makes with no steps).
    IntensityWarpOptions judge = warp;
    judge.levels = {{o.warp.levels.back().imageSigma, o.warp.levels.back().spacingGridPx, 0}};
    const cv::Mat startSeen = labelsUnderMap(atlasLabels, mapX, mapY);
    const std::unordered_set<std::int32_t> graded = gradedRegions(grey, paintWeight, startSeen, o);
    // What a level fits against under a map: the painting (from `painted` pixels), and the
    // weight without the regions left out. `options` holds the level(s).
    auto fit = [&](const cv::Mat& mx, const cv::Mat& my, const cv::Mat& seen,
                   const cv::Mat& painted, const IntensityWarpOptions& options) {
        const cv::Mat plane = paintSeen(grey, painted, seen, atlasLabels, glassIds, o);
        return refineWarpByIntensity(grey, withoutRegions(weight, seen, graded), mx, my, plane,
                                     options);
    };
    const IntensityWarp start = fit(mapX, mapY, startSeen, paintWeight, judge);
    IntensityWarp out;
    out.ux = cv::Mat::zeros(gs, CV_32F);
    out.uy = cv::Mat::zeros(gs, CV_32F);
    out.leftOut.assign(graded.begin(), graded.end());
    std::sort(out.leftOut.begin(), out.leftOut.end());
    out.explainedBefore = out.explainedAfter = start.explainedBefore;
    out.minJacobian = start.minJacobian;
    if (cv::countNonZero(weight) < 64)
        return out;
    // The levels coarse to fine, each painted under the map so far; with `painted` the fitting
    // blocks and `holdOut` the block size, a level that explains less of its own painting on
    // the held-out blocks adds nothing.
    struct Fitted {
        cv::Mat ux, uy;
        double minJacobian = 1;
        int steps = 0;
    };
    auto levels = [&](const cv::Mat& painted, int holdOut) {
        Fitted f{cv::Mat::zeros(gs, CV_32F), cv::Mat::zeros(gs, CV_32F), start.minJacobian, 0};
        for (const IntensityWarpLevel& level : o.warp.levels) {
            const cv::Mat mx = mapX + f.ux, my = mapY + f.uy;
            IntensityWarpOptions one = warp;
            one.levels = {level};
            one.holdOutBlockPx = holdOut;
            const IntensityWarp step =
                fit(mx, my, labelsUnderMap(atlasLabels, mx, my), painted, one);
            if (!step.accepted)
                continue;
            f.ux += step.ux;
            f.uy += step.uy;
            f.minJacobian = step.minJacobian;
            f.steps += step.steps;
        }
        return f;
    };
    const Fitted held = levels(paintWeight, o.warp.holdOutBlockPx);
    out.steps = held.steps;
    if (held.steps == 0)
        return out;
    const cv::Mat endX = mapX + held.ux, endY = mapY + held.uy;
    const IntensityWarp end =
        fit(endX, endY, labelsUnderMap(atlasLabels, endX, endY), paintWeight, judge);
    out.explainedAfter = end.explainedBefore;
    out.accepted = out.explainedAfter >= out.explainedBefore + o.warp.minGain;
    if (!out.accepted)
        return out;
    if (o.warp.holdOutBlockPx > 0 && o.warp.refitOnAll) {
        // Judged on the held-out blocks, the field kept is fitted on every pixel (each level
        // painted from all of them).
        const Fitted all = levels(weight, 0);
        if (all.steps > 0) {
            out.ux = all.ux;
            out.uy = all.uy;
            out.minJacobian = all.minJacobian;
            out.steps += all.steps;
            return out;
        }
    }
    out.ux = held.ux;
    out.uy = held.uy;
    out.minJacobian = held.minJacobian;
    return out;
}

} // namespace slicestation::pipeline
