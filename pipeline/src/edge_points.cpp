#include "slicestation/pipeline/edge_points.hpp"

#include "slicestation/pipeline/point_grid.hpp"

#include <cmath>
#include <unordered_set>

namespace slicestation::pipeline {

std::vector<cv::Point2f> edgePixels(const cv::Mat& edgeImage) {
    CV_Assert(edgeImage.type() == CV_8U);
    std::vector<cv::Point2f> out;
    for (int y = 0; y < edgeImage.rows; ++y) {
        const uchar* row = edgeImage.ptr<uchar>(y);
        for (int x = 0; x < edgeImage.cols; ++x)
            if (row[x])
                out.emplace_back(float(x), float(y));
    }
    return out;
}

std::vector<cv::Point2f> labelBoundarySamples(const cv::Mat& labels) {
    CV_Assert(labels.type() == CV_32S);
    std::vector<cv::Point2f> out;
    for (int y = 0; y < labels.rows; ++y) {
        const int* row = labels.ptr<int>(y);
        const int* next = y + 1 < labels.rows ? labels.ptr<int>(y + 1) : nullptr;
        for (int x = 0; x < labels.cols; ++x) {
            if (x + 1 < labels.cols && row[x + 1] != row[x])
                out.emplace_back(x + 0.5f, float(y));
            if (next && next[x] != row[x])
                out.emplace_back(float(x), y + 0.5f);
        }
    }
    return out;
}

namespace {
long long cellKey(cv::Point2f p, float cell) {
    // Integer cell indices first: adding an offset in float would round them away.
    const long long cx = static_cast<long long>(std::floor(double(p.x) / cell));
    const long long cy = static_cast<long long>(std::floor(double(p.y) / cell));
    return (cy << 32) ^ (cx + (1LL << 31));
}
} // namespace

EdgePoints thinEdgePoints(const EdgePoints& points, float spacing) {
    EdgePoints out;
    std::unordered_set<long long> taken;
    for (size_t i = 0; i < points.size(); ++i) {
        if (!taken.insert(cellKey(points.points[i], spacing)).second)
            continue;
        out.points.push_back(points.points[i]);
        out.normals.push_back(points.normals[i]);
    }
    return out;
}

EdgePoints mlsEdgePoints(const std::vector<cv::Point2f>& raw, float spacing, float radius) {
    EdgePoints out;
    if (raw.empty())
        return out;
    const PointGrid grid(raw, radius);
    const float inv2s2 = 1.0f / (2.0f * (radius / 2) * (radius / 2));
    std::unordered_set<long long> taken;
    const float cell = std::max(spacing, 1e-3f);
    for (const cv::Point2f& p : raw) {
        const long long key = cellKey(p, cell);
        if (taken.count(key))
            continue;
        // Weighted line fit (moving least squares of degree 1) around p.
        double sw = 0, mx = 0, my = 0;
        int n = 0;
        grid.forEachWithin(p, radius, [&](int i, float d2) {
            const double w = std::exp(-d2 * inv2s2);
            sw += w;
            mx += w * raw[i].x;
            my += w * raw[i].y;
            ++n;
        });
        if (n < 3)
            continue;
        mx /= sw;
        my /= sw;
        double cxx = 0, cxy = 0, cyy = 0;
        grid.forEachWithin(p, radius, [&](int i, float d2) {
            const double w = std::exp(-d2 * inv2s2);
            const double dx = raw[i].x - mx, dy = raw[i].y - my;
            cxx += w * dx * dx;
            cxy += w * dx * dy;
            cyy += w * dy * dy;
        });
        // Direction of the line: principal eigenvector of the 2x2 covariance.
        const double theta = 0.5 * std::atan2(2 * cxy, cxx - cyy);
        const double tx = std::cos(theta), ty = std::sin(theta);
        const double nx = -ty, ny = tx;
        const double off = (p.x - mx) * nx + (p.y - my) * ny;
        taken.insert(key);
        out.points.emplace_back(float(p.x - off * nx), float(p.y - off * ny));
        out.normals.emplace_back(float(nx), float(ny));
    }
    return out;
}

} // namespace slicestation::pipeline
