#include "slicestation/sim/section_cells.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <random>
#include <unordered_map>

namespace slicestation::sim {
namespace {

std::uint64_t mix(std::uint64_t x) {
    x += 0x9E3779B97F4A7C15ULL;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
    return x ^ (x >> 31);
}

double unit(std::uint64_t bits) {
    return double(bits >> 11) * 0x1.0p-53;
}

} // namespace

std::vector<TrueCell> placeCells(const cv::Mat& labels, const cv::Mat& tissue, const CellOptions& o,
                                 std::uint64_t seed) {
    std::vector<TrueCell> out;
    if (labels.empty() || labels.type() != CV_32S || tissue.size() != labels.size() ||
        tissue.type() != CV_8U || !(o.diameterPx > 0) || !(o.meanPerMpx > 0))
        return out;
    std::mt19937_64 rng(mix(seed ^ 0xCE11CE11ULL));
    auto uniform = [&rng] { return unit(rng()); };
    // Candidates: every tissue pixel draws with its region's probability, at a random spot
    // inside the pixel; accepted ones keep a hard-core distance (a grid of buckets).
    const double minDist = std::clamp(o.minDistance, 0.5, 3.0) * o.diameterPx;
    const double bucket = std::max(1.0, minDist);
    std::unordered_map<std::int64_t, std::vector<cv::Point2d>> grid;
    auto key = [](std::int64_t gx, std::int64_t gy) { return gx * 1'000'003 + gy; };
    std::unordered_map<std::int32_t, double> density; // per pixel
    for (int y = 0; y < labels.rows; ++y) {
        const std::int32_t* l = labels.ptr<std::int32_t>(y);
        const std::uint8_t* t = tissue.ptr<std::uint8_t>(y);
        for (int x = 0; x < labels.cols; ++x) {
            if (l[x] <= 0 || !t[x])
                continue;
            auto it = density.find(l[x]);
            if (it == density.end()) {
                const double factor = 0.1 + 1.9 * unit(mix(seed ^ mix(std::uint64_t(l[x]))));
                it = density.emplace(l[x], factor * o.meanPerMpx * 1e-6).first;
            }
            if (uniform() >= it->second)
                continue;
            const cv::Point2d p(x - 0.5 + uniform(), y - 0.5 + uniform());
            const auto gx = std::int64_t(std::floor(p.x / bucket));
            const auto gy = std::int64_t(std::floor(p.y / bucket));
            bool close = false;
            for (std::int64_t i = -1; i <= 1 && !close; ++i)
                for (std::int64_t j = -1; j <= 1 && !close; ++j) {
                    auto g = grid.find(key(gx + i, gy + j));
                    if (g != grid.end())
                        for (const cv::Point2d& q : g->second)
                            if (cv::norm(q - p) < minDist) {
                                close = true;
                                break;
                            }
                }
            if (close)
                continue;
            grid[key(gx, gy)].push_back(p);
            out.push_back({p, l[x], true});
        }
    }
    return out;
}

cv::Mat renderCells(cv::Size size, const std::vector<TrueCell>& cells, double diameterPx) {
    cv::Mat out = cv::Mat::zeros(size, CV_32F);
    const double sigma = diameterPx / 2.3548; // FWHM = 2 sqrt(2 ln 2) sigma
    const int reach = int(std::ceil(3 * sigma));
    for (const TrueCell& c : cells) {
        const int cx = int(std::lround(c.image.x)), cy = int(std::lround(c.image.y));
        for (int y = std::max(0, cy - reach); y <= std::min(size.height - 1, cy + reach); ++y) {
            float* p = out.ptr<float>(y);
            for (int x = std::max(0, cx - reach); x <= std::min(size.width - 1, cx + reach); ++x) {
                const double dx = x - c.image.x, dy = y - c.image.y;
                p[x] += float(std::exp(-(dx * dx + dy * dy) / (2 * sigma * sigma)));
            }
        }
    }
    // Touching cells do not add up to a brighter cell: the stain saturates at one cell's worth.
    cv::min(out, 1.0, out);
    return out;
}

void markCounted(std::vector<TrueCell>& cells, const cv::Mat& tissueAfter,
                 const cv::Mat& damageMask) {
    for (TrueCell& c : cells) {
        const int x = int(std::lround(c.image.x)), y = int(std::lround(c.image.y));
        const bool inside = x >= 0 && y >= 0 && x < tissueAfter.cols && y < tissueAfter.rows;
        c.counted = inside && tissueAfter.at<std::uint8_t>(y, x) != 0 &&
                    (damageMask.empty() || damageMask.at<std::uint8_t>(y, x) == 0);
    }
}

} // namespace slicestation::sim
