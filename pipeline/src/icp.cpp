#include "slicestation/pipeline/icp.hpp"

#include "slicestation/pipeline/affine.hpp"

#include <Eigen/Dense>
#include <opencv2/core/utility.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <utility>

namespace slicestation::pipeline {

namespace {

/// Matching and its consistency check run side by side on OpenCV's threads from this many
/// points (fewer cost less than handing them out).
constexpr size_t kParallelMatches = 512;

/// A set of ranks 0..n-1 (each present at most once) with the k-th smallest present rank: a bit
/// per rank, a count per 64-bit word and per block of 8 words. Adding or removing is three
/// stores; the k-th rank skips whole blocks, then words, then bytes of the word. An order
/// statistic of a set that changes a little at a time.
class RankSet {
public:
    explicit RankSet(size_t n)
        : bits_((n + 63) / 64 + 1, 0), wordCount_(bits_.size(), 0),
          blockCount_(bits_.size() / 8 + 1, 0) {}
    void add(int rank) {
        const auto r = size_t(rank);
        bits_[r / 64] |= uint64_t(1) << (r % 64);
        ++wordCount_[r / 64];
        ++blockCount_[r / 512];
    }
    void remove(int rank) {
        const auto r = size_t(rank);
        bits_[r / 64] &= ~(uint64_t(1) << (r % 64));
        --wordCount_[r / 64];
        --blockCount_[r / 512];
    }
    /// The rank at 0-based position `k` in the sorted present ranks (k below the count).
    int kth(int k) const {
        size_t b = 0;
        while (blockCount_[b] <= k)
            k -= blockCount_[b++];
        size_t w = b * 8;
        while (wordCount_[w] <= k)
            k -= wordCount_[w++];
        uint64_t word = bits_[w];
        int base = int(w * 64);
        for (;;) {
            const int inByte = kBitsInByte[word & 0xff];
            if (inByte > k)
                break;
            k -= inByte;
            word >>= 8;
            base += 8;
        }
        for (;; word >>= 1, ++base)
            if ((word & 1) && k-- == 0)
                return base;
    }

private:
    static constexpr std::array<uint8_t, 256> kBitsInByte = [] {
        std::array<uint8_t, 256> t{};
        for (int i = 0; i < 256; ++i)
            t[size_t(i)] = uint8_t((i & 1) + t[size_t(i / 2)]);
        return t;
    }();
    std::vector<uint64_t> bits_;
    std::vector<int> wordCount_, blockCount_;
};

/// Ranks of `v` (ties in any order: tied ranks hold equal values, so an order statistic's value
/// does not depend on it) and the values in rank order. The values are sorted with their indices
/// beside them (no indirection in the comparisons).
void rankValues(const std::vector<double>& v, std::vector<int>& rank, std::vector<double>& sorted) {
    std::vector<std::pair<double, int>> order(v.size());
    for (size_t i = 0; i < v.size(); ++i)
        order[i] = {v[i], int(i)};
    std::sort(order.begin(), order.end());
    rank.resize(v.size());
    sorted.resize(v.size());
    for (size_t r = 0; r < order.size(); ++r) {
        rank[size_t(order[r].second)] = int(r);
        sorted[r] = order[r].first;
    }
}

/// For each match k: do the median x and y displacements of the matches within 2 `distance`
/// of it (itself included, at least 3) lie within distance / 2 of its own? The medians are the
/// exact order statistics of each neighbourhood; the neighbourhoods are visited in grid order
/// and kept as sets of ranks that change only by the points entering and leaving, so each median
/// costs a short scan of counts instead of a selection over the whole neighbourhood.
std::vector<char> consistentWithNeighbours(const std::vector<cv::Point2f>& at,
                                           const std::vector<cv::Point2d>& disp,
                                           const PointGrid& grid, double distance) {
    const size_t n = at.size();
    std::vector<double> xs(n), ys(n), sortedX, sortedY;
    for (size_t k = 0; k < n; ++k) {
        xs[k] = disp[k].x;
        ys[k] = disp[k].y;
    }
    std::vector<int> rankX, rankY;
    rankValues(xs, rankX, sortedX);
    rankValues(ys, rankY, sortedY);
    // Visit in cell order, rows alternating direction, so that consecutive neighbourhoods
    // overlap.
    float x0 = at[0].x, y0 = at[0].y;
    for (const cv::Point2f& p : at) {
        x0 = std::min(x0, p.x);
        y0 = std::min(y0, p.y);
    }
    const double cell = std::max(distance / 4, 1e-3);
    // One key per match: the cell row, then the column (negated in odd rows), then the match.
    std::vector<std::pair<std::uint64_t, int>> visit(n);
    for (size_t k = 0; k < n; ++k) {
        const auto cy = std::int64_t(std::floor((at[k].y - y0) / cell));
        const auto cx = std::int64_t(std::floor((at[k].x - x0) / cell));
        const std::int64_t along = cy % 2 ? -cx : cx;
        visit[k] = {(std::uint64_t(cy) << 32) + std::uint64_t(along + (std::int64_t(1) << 31)),
                    int(k)};
    }
    std::sort(visit.begin(), visit.end());
    std::vector<char> keep(n, 0);
    // The visit is cut into consecutive stretches, one per thread, each with its own sets: a
    // match's medians are exact, so its verdict does not depend on the cut.
    const int stretches = n >= kParallelMatches ? std::max(1, std::min(cv::getNumThreads(), 8)) : 1;
    cv::parallel_for_(
        cv::Range(0, stretches),
        [&](const cv::Range& range) {
            for (int t = range.start; t < range.end; ++t) {
                const size_t v0 = n * size_t(t) / size_t(stretches);
                const size_t v1 = n * size_t(t + 1) / size_t(stretches);
                RankSet countX(n), countY(n);
                std::vector<int> stamp(n, -1), members;
                std::vector<char> in(n, 0);
                for (size_t v = v0; v < v1; ++v) {
                    const int k = visit[v].second;
                    int count = 0;
                    grid.forEachWithin(at[size_t(k)], float(2 * distance), [&](int j, float) {
                        stamp[size_t(j)] = int(v);
                        ++count;
                        if (!in[size_t(j)]) {
                            in[size_t(j)] = 1;
                            countX.add(rankX[size_t(j)]);
                            countY.add(rankY[size_t(j)]);
                            members.push_back(j);
                        }
                    });
                    size_t w = 0;
                    for (const int j : members) {
                        if (stamp[size_t(j)] == int(v)) {
                            members[w++] = j;
                        } else {
                            in[size_t(j)] = 0;
                            countX.remove(rankX[size_t(j)]);
                            countY.remove(rankY[size_t(j)]);
                        }
                    }
                    members.resize(w);
                    if (count < 3)
                        continue; // an isolated match has nothing to agree with
                    const int mid = count / 2;
                    const double dx = disp[size_t(k)].x - sortedX[size_t(countX.kth(mid))];
                    const double dy = disp[size_t(k)].y - sortedY[size_t(countY.kth(mid))];
                    keep[size_t(k)] = dx * dx + dy * dy <= 0.25 * distance * distance;
                }
            }
        },
        stretches);
    return keep;
}

} // namespace

std::vector<Match> findMatches(const std::vector<cv::Point2f>& mappedPoints,
                               const std::vector<cv::Point2f>& mappedNormals,
                               const EdgePoints& target, const PointGrid& targetGrid,
                               double distance, double angleDeg, bool consistencyCheck,
                               TargetRule rule) {
    const double cosMax = std::cos(angleDeg * CV_PI / 180.0);
    const bool weighted = rule == TargetRule::WeightedAverage;
    // Each point's match in its own slot (side by side on OpenCV's threads), then gathered in
    // the points' order: the same matches whatever the threads.
    const size_t n = mappedPoints.size();
    std::vector<Match> slot(n);
    std::vector<char> found(n, 0);
    const auto matchRange = [&](const cv::Range& range) {
        for (int ii = range.start; ii < range.end; ++ii) {
            const auto i = size_t(ii);
            const cv::Point2f q = mappedPoints[i];
            const cv::Point2f nq = mappedNormals[i];
            double sw = 0, sx = 0, sy = 0;
            int nearest = -1;
            float nearestD2 = 0;
            targetGrid.forEachWithin(q, float(distance), [&](int j, float d2) {
                const cv::Point2f m = target.normals[size_t(j)];
                if (std::abs(m.x * nq.x + m.y * nq.y) < cosMax)
                    return;
                if (nearest < 0 || d2 < nearestD2) {
                    nearest = j;
                    nearestD2 = d2;
                }
                if (!weighted)
                    return;
                // Eq. 1: weight 1/d, and 100 for an exact hit.
                const double d = std::sqrt(double(d2));
                const double w = d < 1e-9 ? 100.0 : 1.0 / d;
                sw += w;
                sx += w * target.points[size_t(j)].x;
                sy += w * target.points[size_t(j)].y;
            });
            if (nearest < 0)
                continue;
            found[i] = 1;
            if (weighted) {
                slot[i] = {ii, {sx / sw, sy / sw}};
            } else {
                const cv::Point2d a = target.points[size_t(nearest)];
                const cv::Point2d m = target.normals[size_t(nearest)];
                const double along = (a - cv::Point2d(q)).dot(m);
                slot[i] = {ii, cv::Point2d(q) + m * along};
            }
        }
    };
    const cv::Range all(0, int(n));
    if (n >= kParallelMatches)
        cv::parallel_for_(all, matchRange, double(n) / 128);
    else
        matchRange(all);
    std::vector<Match> matches;
    matches.reserve(n);
    for (size_t i = 0; i < n; ++i)
        if (found[i])
            matches.push_back(slot[i]);
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
    const std::vector<char> keep = consistentWithNeighbours(at, disp, grid, distance);
    std::vector<Match> kept;
    kept.reserve(matches.size());
    for (size_t k = 0; k < matches.size(); ++k)
        if (keep[k])
            kept.push_back(matches[k]);
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
