#pragma once
/// A uniform-grid spatial index over 2-D points for fixed-radius neighbour queries.

#include <opencv2/core.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

namespace slicestation::pipeline {

/// Buckets points into square cells of side `cellSize`. Borrows nothing: points are copied.
class PointGrid {
public:
    PointGrid(const std::vector<cv::Point2f>& points, float cellSize);

    /// Calls fn(index, squaredDistance) for every point within `radius` of p (radius <= a few
    /// cells keeps this fast).
    template <class Fn> void forEachWithin(cv::Point2f p, float radius, Fn&& fn) const {
        const int cx0 = cellX(p.x - radius), cx1 = cellX(p.x + radius);
        const int cy0 = cellY(p.y - radius), cy1 = cellY(p.y + radius);
        const float r2 = radius * radius;
        for (int cy = cy0; cy <= cy1; ++cy) {
            // The cells of a row are consecutive in the cell order: one stretch of points.
            const int row = cy * cols_;
            for (int k = start_[row + cx0], end = start_[row + cx1 + 1]; k < end; ++k) {
                const float dx = sorted_[k].x - p.x, dy = sorted_[k].y - p.y;
                const float d2 = dx * dx + dy * dy;
                if (d2 <= r2)
                    fn(order_[k], d2);
            }
        }
    }
    /// Index of the nearest point within `radius`, or -1.
    int nearest(cv::Point2f p, float radius) const;

    const std::vector<cv::Point2f>& points() const { return points_; }

private:
    // Inline: every query computes four of them (perf: 1% of a registration as calls).
    int cellX(float x) const {
        return std::clamp(static_cast<int>(std::floor((x - x0_) / cell_)), 0, cols_ - 1);
    }
    int cellY(float y) const {
        return std::clamp(static_cast<int>(std::floor((y - y0_) / cell_)), 0, rows_ - 1);
    }

    std::vector<cv::Point2f> points_;
    std::vector<int> order_;          ///< point indices sorted by cell
    std::vector<cv::Point2f> sorted_; ///< the points in that order (read in stretches)
    std::vector<int> start_;          ///< cell -> first position in order_ (size cells + 1)
    float cell_ = 1.0f;
    float x0_ = 0.0f, y0_ = 0.0f;
    int cols_ = 1, rows_ = 1;
};

} // namespace slicestation::pipeline
