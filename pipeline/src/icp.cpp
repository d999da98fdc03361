#include "slicestation/pipeline/icp.hpp"

#include "slicestation/pipeline/affine.hpp"

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>

namespace slicestation::pipeline {

std::vector<Match> findMatches(const std::vector<cv::Point2f>& mappedPoints,
                               const std::vector<cv::Point2f>& mappedNormals,
                               const EdgePoints& target, const PointGrid& targetGrid,
                               double distance, double angleDeg, bool consistencyCheck,
                               TargetRule rule) {
    const double cosMax = std::cos(angleDeg * CV_PI / 180.0);
    std::vector<Match> matches;
    matches.reserve(mappedPoints.size());
    for (size_t i = 0; i < mappedPoints.size(); ++i) {
        const cv::Point2f q = mappedPoints[i];
        const cv::Point2f n = mappedNormals[i];
        double sw = 0, sx = 0, sy = 0;
        int nearest = -1;
        float nearestD2 = 0;
        targetGrid.forEachWithin(q, float(distance), [&](int j, float d2) {
            const cv::Point2f m = target.normals[j];
            if (std::abs(m.x * n.x + m.y * n.y) < cosMax)
                return;
            if (nearest < 0 || d2 < nearestD2) {
                nearest = j;
                nearestD2 = d2;
            }
            // Eq. 1: weight 1/d, and 100 for an exact hit.
            const double d = std::sqrt(double(d2));
            const double w = d < 1e-9 ? 100.0 : 1.0 / d;
            sw += w;
            sx += w * target.points[j].x;
            sy += w * target.points[j].y;
        });
        if (nearest < 0)
            continue;
        if (rule == TargetRule::WeightedAverage) {
            matches.push_back({static_cast<int>(i), {sx / sw, sy / sw}});
        } else {
            const cv::Point2d a = target.points[nearest];
            const cv::Point2d m = target.normals[nearest];
            const double along = (a - cv::Point2d(q)).dot(m);
            matches.push_back({static_cast<int>(i), cv::Point2d(q) + m * along});
        }
    }
    if (!consistencyCheck || matches.size() < 8)
        return matches;

    // Neighbourhood consistency: neighbouring source points should move alike.
    std::vector<cv::Point2f> at(matches.size());
    std::vector<cv::Point2d> disp(matches.size());
    for (size_t k = 0; k < matches.size(); ++k) {
        at[k] = mappedPoints[matches[k].source];
        disp[k] = matches[k].target - cv::Point2d(at[k]);
    }
    const PointGrid grid(at, float(distance));
    std::vector<Match> kept;
    kept.reserve(matches.size());
    std::vector<double> xs, ys;
    for (size_t k = 0; k < matches.size(); ++k) {
        xs.clear();
        ys.clear();
        grid.forEachWithin(at[k], float(2 * distance), [&](int j, float) {
            xs.push_back(disp[j].x);
            ys.push_back(disp[j].y);
        });
        if (xs.size() < 3)
            continue; // an isolated match has nothing to agree with
        auto mid = xs.size() / 2;
        std::nth_element(xs.begin(), xs.begin() + static_cast<std::ptrdiff_t>(mid), xs.end());
        std::nth_element(ys.begin(), ys.begin() + static_cast<std::ptrdiff_t>(mid), ys.end());
        const double dx = disp[k].x - xs[mid], dy = disp[k].y - ys[mid];
        if (std::hypot(dx, dy) <= 0.5 * distance)
            kept.push_back(matches[k]);
    }
    return kept;
}

bool fitAffine(const std::vector<cv::Point2f>& source, const std::vector<Match>& matches,
               cv::Matx23d& out) {
    if (matches.size() < 3)
        return false;
    // Normal equations of Z T_1 = b_x and Z T_2 = b_y, centred for conditioning.
    double cx = 0, cy = 0;
    for (const auto& m : matches) {
        cx += source[m.source].x;
        cy += source[m.source].y;
    }
    cx /= double(matches.size());
    cy /= double(matches.size());
    Eigen::Matrix3d ztz = Eigen::Matrix3d::Zero();
    Eigen::Vector3d ztx = Eigen::Vector3d::Zero(), zty = Eigen::Vector3d::Zero();
    for (const auto& m : matches) {
        const Eigen::Vector3d z(source[m.source].x - cx, source[m.source].y - cy, 1.0);
        ztz += z * z.transpose();
        ztx += z * m.target.x;
        zty += z * m.target.y;
    }
    const Eigen::LDLT<Eigen::Matrix3d> ldlt(ztz);
    if (ldlt.info() != Eigen::Success || std::abs(ztz.determinant()) < 1e-9)
        return false;
    const Eigen::Vector3d t1 = ldlt.solve(ztx), t2 = ldlt.solve(zty);
    if (!t1.allFinite() || !t2.allFinite())
        return false;
    out = cv::Matx23d(t1[0], t1[1], t1[2] - t1[0] * cx - t1[1] * cy, t2[0], t2[1],
                      t2[2] - t2[0] * cx - t2[1] * cy);
    return true;
}

IcpResult icpAffine(const EdgePoints& source, const EdgePoints& target, const PointGrid& targetGrid,
                    const cv::Matx23d& init, const IcpOptions& options) {
    IcpResult r;
    r.targetFromSource = init;
    const double initDet = std::abs(det(init));
    std::vector<cv::Point2f> mp(source.size()), mn(source.size());
    for (const IcpLevel& level : options.levels) {
        for (int it = 0; it < options.maxIterationsPerLevel; ++it) {
            const cv::Matx23d& t = r.targetFromSource;
            for (size_t i = 0; i < source.size(); ++i) {
                mp[i] = apply(t, source.points[i]);
                mn[i] = mapNormal(t, source.normals[i]);
            }
            auto matches = findMatches(mp, mn, target, targetGrid, level.distance, level.angleDeg,
                                       options.consistencyCheck);
            ++r.iterations;
            if (static_cast<int>(matches.size()) < options.minMatches)
                break;
            cv::Matx23d next;
            if (!fitAffine(source.points, matches, next))
                break;
            // Guard against collapse: a fit that shrinks or blows up the section is wrong.
            const double ratio = std::abs(det(next)) / std::max(initDet, 1e-12);
            if (!(ratio > 0.4 && ratio < 2.5))
                break;
            double motion = 0;
            for (size_t i = 0; i < source.size(); i += 7)
                motion =
                    std::max(motion, cv::norm(apply(next, source.points[i]) - cv::Point2d(mp[i])));
            r.targetFromSource = next;
            r.matches = std::move(matches);
            if (motion < options.settleDistance)
                break;
        }
    }
    double ss = 0;
    for (const auto& m : r.matches)
        ss += std::pow(cv::norm(apply(r.targetFromSource, source.points[m.source]) - m.target), 2);
    r.rmsResidual = r.matches.empty() ? 0 : std::sqrt(ss / double(r.matches.size()));
    return r;
}

} // namespace slicestation::pipeline
