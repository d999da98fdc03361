#include "slicestation/daemon/station/autofocus.hpp"

#include "slicestation/daemon/station/retry_policy.hpp"
#include "slicestation/pipeline/focus_measures.hpp"
#include "slicestation/pipeline/frame_image.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;

struct Sample {
    double zUm = 0;
    double score = 0;
};

class Search {
public:
    Search(hw::Stage& stage, hw::Camera& camera, const hw::StagePosition& at,
           const AutofocusSettings& s)
        : stage_(stage), camera_(camera), at_(at), s_(s) {}

    core::Result<void> moveZ(double zUm) {
        auto moved =
            moveWithRetries(stage_, {at_.xUm, at_.yUm, zUm}, s_.moveTimeout, s_.moveRetries);
        if (!moved) {
            failed_ = FocusFailure::Stage;
            return moved.error();
        }
        currentZ_ = zUm;
        return {};
    }
    /// Moves to `zUm`, captures, and returns the frame as an image.
    core::Result<cv::Mat> frameAt(double zUm) {
        if (auto moved = moveZ(zUm); !moved)
            return moved.error();
        auto frame = captureWithRetries(camera_, s_.captureTimeout, s_.captureRetries, s_.camera);
        if (!frame) {
            failed_ = FocusFailure::Camera;
            return frame.error();
        }
        ++captures_;
        return pipeline::frameToMat(*frame);
    }
    /// Samples z values low to high, each approached from below.
    core::Result<std::vector<Sample>> sweep(const std::vector<double>& zs, double zMin) {
        std::vector<Sample> out;
        if (zs.empty())
            return out;
        if (currentZ_ > zs.front()) {
            // Come from below, like every later step of the sweep (same backlash side).
            if (auto moved = moveZ(std::max(zMin, zs.front() - s_.coarseStepUm)); !moved) {
                return moved.error();
            }
        }
        for (const double z : zs) {
            auto image = frameAt(z);
            if (!image)
                return image.error();
            out.push_back({z, pipeline::focusMeasure(*image)});
        }
        return out;
    }
    int captures() const { return captures_; }
    double currentZ() const { return currentZ_; }
    /// Which device failed the last failing call (Focus when none did).
    FocusFailure failed() const { return failed_; }

private:
    hw::Stage& stage_;
    hw::Camera& camera_;
    hw::StagePosition at_;
    FocusFailure failed_ = FocusFailure::Focus;
    const AutofocusSettings& s_;
    int captures_ = 0;
    double currentZ_ = 0;
};

/// lo, lo + step, ..., up to hi (hi included when within a thousandth of a step).
std::vector<double> steps(double lo, double hi, double step) {
    std::vector<double> zs;
    const int n = static_cast<int>(std::floor((hi - lo) / step + 1e-3)) + 1;
    for (int i = 0; i < n; ++i)
        zs.push_back(lo + i * step);
    return zs;
}

std::size_t best(const std::vector<Sample>& samples) {
    return static_cast<std::size_t>(
        std::max_element(samples.begin(), samples.end(),
                         [](const Sample& a, const Sample& b) { return a.score < b.score; }) -
        samples.begin());
}

core::Result<void> validate(const AutofocusSettings& s) {
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument, "autofocus settings: " + what);
    };
    if (!(s.coarseStepUm > 0) || !(s.fineStepUm > 0))
        return bad("steps must be > 0");
    if (s.fineStepUm > s.coarseStepUm)
        return bad("fineStepUm must not exceed coarseStepUm");
    if (!(s.rangeUm >= s.coarseStepUm))
        return bad("rangeUm must be at least coarseStepUm");
    if (!(s.minTissueFraction >= 0 && s.minTissueFraction <= 1)) {
        return bad("minTissueFraction must be within [0, 1]");
    }
    if (s.moveTimeout.count() <= 0 || s.captureTimeout.count() <= 0) {
        return bad("timeouts must be > 0");
    }
    return {};
}

core::Result<FocusResult> run(hw::Stage& stage, hw::Camera& camera, const hw::StagePosition& at,
                              const AutofocusSettings& s, FocusFailure& failed) {
    if (auto valid = validate(s); !valid)
        return valid.error();
    const hw::StageLimits limits = stage.limits();
    if (!limits.z) {
        return makeError(ErrorCode::InvalidArgument, "autofocus: the stage has no Z axis");
    }
    const double zMin = limits.z->minUm;
    const double zMax = limits.z->maxUm;

    Search search(stage, camera, at, s);
    struct Report { // tells the caller which device failed, whichever return is taken
        FocusFailure& out;
        const Search& search;
        ~Report() { out = search.failed(); }
    } report{failed, search};
    FocusResult result;
    result.zUm = at.zUm;
    auto first = search.frameAt(at.zUm);
    if (!first)
        return first.error();
    result.captures = search.captures();
    result.score = pipeline::focusMeasure(*first);
    result.tissueFraction = pipeline::tissueFraction(*first);
    if (result.tissueFraction < s.minTissueFraction) {
        return result; // blank glass: nothing to focus on (uScope KB NSC1077)
    }
    result.tissueFound = true;

    const double lo = std::max(zMin, at.zUm - s.rangeUm / 2);
    const double hi = std::min(zMax, at.zUm + s.rangeUm / 2);
    auto coarse = search.sweep(steps(lo, hi, s.coarseStepUm), zMin);
    if (!coarse)
        return coarse.error();
    const std::size_t b = best(*coarse);
    result.peakAtRangeEdge = coarse->size() > 1 && (b == 0 || b + 1 == coarse->size());

    const double zc = (*coarse)[b].zUm;
    const double fineLo = std::max(zMin, zc - s.coarseStepUm);
    const double fineHi = std::min(zMax, zc + s.coarseStepUm);
    auto fine = search.sweep(steps(fineLo, fineHi, s.fineStepUm), zMin);
    if (!fine)
        return fine.error();
    const std::size_t f = best(*fine);
    double zBest = (*fine)[f].zUm;
    if (f > 0 && f + 1 < fine->size()) {
        // Parabola through the peak and its neighbours; vertex kept within half a step.
        const double sm = (*fine)[f - 1].score;
        const double s0 = (*fine)[f].score;
        const double sp = (*fine)[f + 1].score;
        const double denominator = sm - 2 * s0 + sp;
        if (denominator < 0) {
            const double offset = std::clamp(0.5 * (sm - sp) / denominator, -0.5, 0.5);
            zBest += offset * s.fineStepUm;
        }
    }
    // Leave the stage in focus, approached from below like the sweep frames.
    if (search.currentZ() > zBest) {
        if (auto moved = search.moveZ(std::max(zMin, zBest - s.coarseStepUm)); !moved) {
            return moved.error();
        }
    }
    if (auto moved = search.moveZ(zBest); !moved)
        return moved.error();

    result.zUm = zBest;
    result.score = (*fine)[f].score;
    result.captures = search.captures();
    return result;
}

} // namespace

core::Result<FocusResult> autofocus(hw::Stage& stage, hw::Camera& camera,
                                    const hw::StagePosition& at, const AutofocusSettings& s,
                                    FocusFailure* failed) {
    FocusFailure ignored = FocusFailure::Focus;
    FocusFailure& out = failed ? *failed : ignored;
    out = FocusFailure::Focus;
    try {
        return run(stage, camera, at, s, out);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal, std::string("autofocus: OpenCV: ") + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, std::string("autofocus: ") + e.what());
    }
}

// ---------------------------------------------------------------------------------------------

void FocusSurface::add(double xUm, double yUm, double zUm) {
    points_.push_back({xUm, yUm, zUm});
}

std::optional<double> FocusSurface::predict(double xUm, double yUm) const {
    if (points_.empty())
        return std::nullopt;
    const double n = static_cast<double>(points_.size());
    double mx = 0, my = 0, mz = 0;
    for (const auto& p : points_) {
        mx += p.x;
        my += p.y;
        mz += p.z;
    }
    mx /= n;
    my /= n;
    mz /= n;
    if (points_.size() < 3)
        return mz; // one or two points: their mean
    // Centred second moments of x/y, and their covariance with z.
    double sxx = 0, sxy = 0, syy = 0, sxz = 0, syz = 0;
    for (const auto& p : points_) {
        const double dx = p.x - mx, dy = p.y - my, dz = p.z - mz;
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
        sxz += dx * dz;
        syz += dy * dz;
    }
    // Eigenvalues of the 2x2 scatter matrix: how far the points spread along their principal
    // directions. A small minor spread (relative) means the points lie on a line.
    const double trace = sxx + syy;
    const double det = sxx * syy - sxy * sxy;
    const double disc = std::sqrt(std::max(0.0, trace * trace / 4 - det));
    const double major = trace / 2 + disc;
    const double minor = trace / 2 - disc;
    if (!(major > 1e-9))
        return mz; // all at the same x/y
    if (minor < 1e-9 * major + 1e-12) {
        // Points on one line: least squares along the principal direction (ux, uy).
        double ux = sxy, uy = major - sxx;
        if (std::abs(ux) + std::abs(uy) < 1e-12) {
            ux = major - syy;
            uy = sxy;
        }
        const double norm = std::hypot(ux, uy);
        ux /= norm;
        uy /= norm;
        double stt = 0, stz = 0;
        for (const auto& p : points_) {
            const double t = (p.x - mx) * ux + (p.y - my) * uy;
            stt += t * t;
            stz += t * (p.z - mz);
        }
        const double t = (xUm - mx) * ux + (yUm - my) * uy;
        return mz + (stz / stt) * t;
    }
    // Plane through the centroid: [sxx sxy; sxy syy] [b; c] = [sxz; syz] (normal equations).
    const double b = (sxz * syy - syz * sxy) / det;
    const double c = (syz * sxx - sxz * sxy) / det;
    return mz + b * (xUm - mx) + c * (yUm - my);
}

} // namespace slicestation::daemon
