#include "slicestation/pipeline/obb.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>

namespace slicestation::pipeline {

OrientedBox orientedBox(const std::vector<cv::Point2f>& points, int samples) {
    OrientedBox box;
    if (points.size() < 3)
        return box;
    std::vector<cv::Point2f> hull;
    cv::convexHull(points, hull);
    if (hull.size() < 3)
        return box;
    double perimeter = 0;
    for (size_t i = 0; i < hull.size(); ++i)
        perimeter += cv::norm(hull[(i + 1) % hull.size()] - hull[i]);
    if (perimeter <= 0)
        return box;

    // Uniform samples along the hull: hull vertices cluster where the outline is curved, and PCA
    // of the vertices would follow that clustering rather than the shape.
    std::vector<cv::Point2d> s;
    s.reserve(samples);
    const double step = perimeter / samples;
    double carry = 0;
    for (size_t i = 0; i < hull.size(); ++i) {
        const cv::Point2d a = hull[i], b = hull[(i + 1) % hull.size()];
        const double len = cv::norm(b - a);
        double t = carry;
        while (t < len) {
            s.push_back(a + (b - a) * (t / len));
            t += step;
        }
        carry = t - len;
    }
    cv::Point2d c(0, 0);
    for (const auto& p : s)
        c += p;
    c *= 1.0 / double(s.size());
    double cxx = 0, cxy = 0, cyy = 0;
    for (const auto& p : s) {
        const cv::Point2d d = p - c;
        cxx += d.x * d.x;
        cxy += d.x * d.y;
        cyy += d.y * d.y;
    }
    const double theta = 0.5 * std::atan2(2 * cxy, cxx - cyy);
    box.major = {std::cos(theta), std::sin(theta)};
    box.minor = {-box.major[1], box.major[0]};
    double u0 = 1e300, u1 = -1e300, v0 = 1e300, v1 = -1e300;
    for (const auto& h : hull) {
        const cv::Point2d d = cv::Point2d(h) - c;
        const double u = d.x * box.major[0] + d.y * box.major[1];
        const double v = d.x * box.minor[0] + d.y * box.minor[1];
        u0 = std::min(u0, u);
        u1 = std::max(u1, u);
        v0 = std::min(v0, v);
        v1 = std::max(v1, v);
    }
    // The box centre is the middle of the extents, not the sample mean.
    const double um = 0.5 * (u0 + u1), vm = 0.5 * (v0 + v1);
    box.centre = c + cv::Point2d(box.major[0] * um + box.minor[0] * vm,
                                 box.major[1] * um + box.minor[1] * vm);
    box.halfMajor = 0.5 * (u1 - u0);
    box.halfMinor = 0.5 * (v1 - v0);
    return box;
}

} // namespace slicestation::pipeline
