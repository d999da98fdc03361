#pragma once
/// Small helpers for 2x3 affine transforms (named by their frames, e.g. atlasFromImage).

#include <opencv2/core.hpp>

#include <cmath>

namespace slicestation::pipeline {

inline cv::Point2d apply(const cv::Matx23d& a, cv::Point2d p) {
    return {a(0, 0) * p.x + a(0, 1) * p.y + a(0, 2), a(1, 0) * p.x + a(1, 1) * p.y + a(1, 2)};
}

/// a after b: apply b first.
inline cv::Matx23d compose(const cv::Matx23d& a, const cv::Matx23d& b) {
    const cv::Matx33d A(a(0, 0), a(0, 1), a(0, 2), a(1, 0), a(1, 1), a(1, 2), 0, 0, 1);
    const cv::Matx33d B(b(0, 0), b(0, 1), b(0, 2), b(1, 0), b(1, 1), b(1, 2), 0, 0, 1);
    const cv::Matx33d C = A * B;
    return {C(0, 0), C(0, 1), C(0, 2), C(1, 0), C(1, 1), C(1, 2)};
}

/// Inverse of an invertible affine.
inline cv::Matx23d invert(const cv::Matx23d& a) {
    const double d = a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0);
    const double i00 = a(1, 1) / d, i01 = -a(0, 1) / d, i10 = -a(1, 0) / d, i11 = a(0, 0) / d;
    return {i00, i01, -(i00 * a(0, 2) + i01 * a(1, 2)), i10, i11, -(i10 * a(0, 2) + i11 * a(1, 2))};
}

/// Determinant of the linear part.
inline double det(const cv::Matx23d& a) {
    return a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0);
}

/// Maps a normal through the linear part (inverse transpose) and renormalises.
inline cv::Point2d mapNormal(const cv::Matx23d& a, cv::Point2d n) {
    // inverse transpose of [[a b][c d]] is 1/det [[d -c][-b a]]
    const cv::Point2d m(a(1, 1) * n.x - a(1, 0) * n.y, -a(0, 1) * n.x + a(0, 0) * n.y);
    const double len = std::hypot(m.x, m.y);
    return len > 0 ? m * (1.0 / len) : n;
}

/// Uniform scale s about the origin, then translation.
inline cv::Matx23d scaling(double s) {
    return {s, 0, 0, 0, s, 0};
}

} // namespace slicestation::pipeline
