#include "slicestation/pipeline/point_grid.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace slicestation::pipeline {

PointGrid::PointGrid(const std::vector<cv::Point2f>& points, float cellSize)
    : points_(points), cell_(std::max(cellSize, 1e-3f)) {
    if (points_.empty()) {
        start_.assign(2, 0);
        return;
    }
    float x1 = x0_ = points_[0].x, y1 = y0_ = points_[0].y;
    for (const auto& p : points_) {
        x0_ = std::min(x0_, p.x);
        y0_ = std::min(y0_, p.y);
        x1 = std::max(x1, p.x);
        y1 = std::max(y1, p.y);
    }
    cols_ = static_cast<int>((x1 - x0_) / cell_) + 1;
    rows_ = static_cast<int>((y1 - y0_) / cell_) + 1;
    std::vector<int> cellOf(points_.size());
    start_.assign(static_cast<size_t>(cols_) * rows_ + 1, 0);
    for (size_t i = 0; i < points_.size(); ++i) {
        cellOf[i] = cellY(points_[i].y) * cols_ + cellX(points_[i].x);
        ++start_[cellOf[i] + 1];
    }
    for (size_t c = 1; c < start_.size(); ++c)
        start_[c] += start_[c - 1];
    order_.resize(points_.size());
    std::vector<int> fill(start_.begin(), start_.end() - 1);
    for (size_t i = 0; i < points_.size(); ++i)
        order_[fill[cellOf[i]]++] = static_cast<int>(i);
    sorted_.resize(points_.size());
    for (size_t k = 0; k < order_.size(); ++k)
        sorted_[k] = points_[size_t(order_[k])];
}

int PointGrid::nearest(cv::Point2f p, float radius) const {
    int best = -1;
    float bestD2 = std::numeric_limits<float>::max();
    forEachWithin(p, radius, [&](int i, float d2) {
        if (d2 < bestD2) {
            bestD2 = d2;
            best = i;
        }
    });
    return best;
}

} // namespace slicestation::pipeline
