#include "slicestation/pipeline/laplace_warp.hpp"

#include "side_by_side.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <cstddef>

namespace slicestation::pipeline {

DisplacementField::DisplacementField(cv::Mat dx, cv::Mat dy, double cellPx)
    : dx_(std::move(dx)), dy_(std::move(dy)), cellPx_(cellPx) {
    CV_Assert(dx_.type() == CV_32F && dy_.type() == CV_32F && dx_.size() == dy_.size());
}

cv::Point2d DisplacementField::at(cv::Point2d p) const {
    if (dx_.empty())
        return {0, 0};
    const double gx = std::clamp(p.x / cellPx_, 0.0, double(dx_.cols - 1));
    const double gy = std::clamp(p.y / cellPx_, 0.0, double(dx_.rows - 1));
    const int x0 = std::min(static_cast<int>(gx), dx_.cols - 2 < 0 ? 0 : dx_.cols - 2);
    const int y0 = std::min(static_cast<int>(gy), dx_.rows - 2 < 0 ? 0 : dx_.rows - 2);
    const int x1 = std::min(x0 + 1, dx_.cols - 1), y1 = std::min(y0 + 1, dx_.rows - 1);
    const double fx = gx - x0, fy = gy - y0;
    auto bil = [&](const cv::Mat& m) {
        return (1 - fy) * ((1 - fx) * m.at<float>(y0, x0) + fx * m.at<float>(y0, x1)) +
               fy * ((1 - fx) * m.at<float>(y1, x0) + fx * m.at<float>(y1, x1));
    };
    return {bil(dx_), bil(dy_)};
}

namespace {

struct Level {
    double cell;
    cv::Mat fixedX, fixedY; ///< CV_32F constrained values
    cv::Mat isFixed;        ///< CV_8U
};

Level makeLevel(cv::Size domain, double cell, const std::vector<cv::Point2d>& pts,
                const std::vector<cv::Point2d>& disp) {
    const int cols = static_cast<int>(std::ceil((domain.width - 1) / cell)) + 1;
    const int rows = static_cast<int>(std::ceil((domain.height - 1) / cell)) + 1;
    Level l{cell, cv::Mat::zeros(rows, cols, CV_32F), cv::Mat::zeros(rows, cols, CV_32F),
            cv::Mat::zeros(rows, cols, CV_8U)};
    cv::Mat count = cv::Mat::zeros(rows, cols, CV_32F);
    for (size_t k = 0; k < pts.size(); ++k) {
        const int j = std::clamp(static_cast<int>(std::lround(pts[k].x / cell)), 0, cols - 1);
        const int i = std::clamp(static_cast<int>(std::lround(pts[k].y / cell)), 0, rows - 1);
        l.fixedX.at<float>(i, j) += float(disp[k].x);
        l.fixedY.at<float>(i, j) += float(disp[k].y);
        count.at<float>(i, j) += 1.0f;
    }
    for (int i = 0; i < rows; ++i)
        for (int j = 0; j < cols; ++j)
            if (const float c = count.at<float>(i, j); c > 0) {
                l.fixedX.at<float>(i, j) /= c;
                l.fixedY.at<float>(i, j) /= c;
                l.isFixed.at<uchar>(i, j) = 1;
            }
    return l;
}

/// SOR sweeps of the five-point Laplacian (Eq. 5 of the paper) with Dirichlet nodes held and
/// mirror (Neumann) borders, in the usual row-by-row order, of one component. Each row is a
/// chain of dependent updates (seven float operations, each waiting for the one before); to keep
/// the processor busy, a band of kBand rows is updated at a time, each row a node behind the one
/// above it (a wavefront), so that the band's updates at one step are independent of each other:
/// every node still reads exactly the values it reads in plain row order (its left and upper
/// neighbours updated, its right and lower ones not yet), so the result is the same to the bit.
void relaxOne(cv::Mat& u, const cv::Mat& fixed, const cv::Mat& isFixed, int sweeps, double w) {
    constexpr int kBand = 8;
    const int rows = u.rows, cols = u.cols;
    const float wf = float(w);
    const auto update = [&](int i, int j) {
        if (isFixed.ptr<uchar>(i)[j]) {
            u.ptr<float>(i)[j] = fixed.ptr<float>(i)[j];
            return;
        }
        const int iu = i > 0 ? i - 1 : std::min(1, rows - 1);
        const int id = i + 1 < rows ? i + 1 : std::max(rows - 2, 0);
        const int jl = j > 0 ? j - 1 : std::min(1, cols - 1);
        const int jr = j + 1 < cols ? j + 1 : std::max(cols - 2, 0);
        float* r = u.ptr<float>(i);
        const float avg = 0.25f * (r[jl] + r[jr] + u.ptr<float>(iu)[j] + u.ptr<float>(id)[j]);
        r[j] += wf * (avg - r[j]);
    };
    // Row strides, in elements.
    const auto us = std::ptrdiff_t(u.step1()), vs = std::ptrdiff_t(fixed.step1()),
               hs = std::ptrdiff_t(isFixed.step1());
    for (int s = 0; s < sweeps; ++s) {
        for (int i = 0, band = 1; i < rows; i += band) {
            // The grid's first and last rows (mirror borders) on their own, the rows between
            // in bands.
            band = i == 0 || i == rows - 1 ? 1 : std::min(kBand, rows - 1 - i);
            // A band's rows are interior (both neighbour rows inside the grid) unless it is the
            // first or last row. Row r's node t - r is a diagonal step (one row down, one node
            // left) from row r - 1's; away from the grid's edges a node is updated on strides,
            // without mirror indices.
            const bool interior = i >= 1 && i + band + 1 <= rows;
            float* const x0 = u.ptr<float>(i);
            const float* const v0 = fixed.ptr<float>(i);
            const uchar* const h0 = isFixed.ptr<uchar>(i);
            const auto inner = [&](float* x, const float* v, const uchar* h) {
                if (*h) {
                    *x = *v;
                    return;
                }
                const float avg = 0.25f * (x[-1] + x[1] + x[-us] + x[us]);
                *x += wf * (avg - *x);
            };
            // Step t updates node t - r of row r; at the steps from `first` to `last` every row
            // of the band is at an interior column (1 .. cols - 2).
            const int first = band, last = cols - 2;
            const auto edgeStep = [&](int t) {
                for (int r = 0; r < band; ++r) {
                    const int j = t - r;
                    if (interior && j >= 1 && j + 1 < cols)
                        inner(x0 + r * us + j, v0 + r * vs + j, h0 + r * hs + j);
                    else if (j >= 0 && j < cols)
                        update(i + r, j);
                }
            };
            int t = 0;
            if (!interior || first > last) {
                for (; t < cols + band - 1; ++t)
                    edgeStep(t);
                continue;
            }
            for (; t < first; ++t)
                edgeStep(t);
            for (; t <= last; ++t) {
                float* x = x0 + t;
                const float* v = v0 + t;
                const uchar* h = h0 + t;
                for (int r = 0; r < band; ++r, x += us - 1, v += vs - 1, h += hs - 1)
                    inner(x, v, h);
            }
            for (; t < cols + band - 1; ++t)
                edgeStep(t);
        }
    }
}

/// Both components, which do not interact: side by side on OpenCV's threads.
void relax(cv::Mat& ux, const cv::Mat& fixedX, cv::Mat& uy, const cv::Mat& fixedY,
           const cv::Mat& isFixed, int sweeps, double w) {
    runTasks(2, [&](int c) {
        if (c == 0)
            relaxOne(ux, fixedX, isFixed, sweeps, w);
        else
            relaxOne(uy, fixedY, isFixed, sweeps, w);
    });
}

} // namespace

DisplacementField solveLaplaceWarp(cv::Size domain, const std::vector<cv::Point2d>& points,
                                   const std::vector<cv::Point2d>& displacements,
                                   const LaplaceOptions& options) {
    CV_Assert(points.size() == displacements.size());
    if (points.empty() || domain.area() == 0)
        return {};
    // Levels from coarse to fine; each coarse level gives the next its starting guess, which is
    // what makes plain relaxation converge in a few dozen sweeps (a cascadic multigrid).
    std::vector<double> cells{options.cellPx};
    while (std::min(domain.width, domain.height) / (cells.back() * 2) >= options.coarsestNodes)
        cells.push_back(cells.back() * 2);
    std::reverse(cells.begin(), cells.end());

    cv::Mat ux, uy;
    for (size_t li = 0; li < cells.size(); ++li) {
        Level l = makeLevel(domain, cells[li], points, displacements);
        int sweeps = options.sweepsPerLevel;
        if (li == 0) {
            const cv::Scalar mx = cv::mean(l.fixedX, l.isFixed), my = cv::mean(l.fixedY, l.isFixed);
            ux = cv::Mat(l.fixedX.size(), CV_32F, cv::Scalar(mx[0]));
            uy = cv::Mat(l.fixedX.size(), CV_32F, cv::Scalar(my[0]));
            sweeps = options.sweepsCoarsest;
        } else {
            // Prolongation: node positions scale exactly by two (x = j * cell).
            cv::Mat nx(l.fixedX.size(), CV_32F), ny(l.fixedX.size(), CV_32F);
            cv::Mat mapX(l.fixedX.size(), CV_32F), mapY(l.fixedX.size(), CV_32F);
            const double ratio = cells[li] / cells[li - 1];
            for (int i = 0; i < mapX.rows; ++i)
                for (int j = 0; j < mapX.cols; ++j) {
                    mapX.at<float>(i, j) = float(j * ratio);
                    mapY.at<float>(i, j) = float(i * ratio);
                }
            cv::remap(ux, nx, mapX, mapY, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
            cv::remap(uy, ny, mapX, mapY, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
            ux = nx;
            uy = ny;
        }
        relax(ux, l.fixedX, uy, l.fixedY, l.isFixed, sweeps, options.relaxation);
    }
    return {ux, uy, options.cellPx};
}

DisplacementField relaxWithin(const DisplacementField& field, const cv::Mat& region, int sweeps,
                              double relaxation) {
    CV_Assert(region.type() == CV_8U);
    if (field.empty() || region.size() != field.dx().size())
        return field;
    const cv::Rect grid(0, 0, region.cols, region.rows);
    const cv::Rect free = cv::boundingRect(region);
    if (free.area() == 0)
        return field;
    // The free nodes and a ring of held ones around them (the grid's own edge mirrors).
    const cv::Rect roi = cv::Rect(free.x - 1, free.y - 1, free.width + 2, free.height + 2) & grid;
    cv::Mat ux = field.dx().clone(), uy = field.dy().clone();
    const cv::Mat held = region(roi) == 0;
    cv::Mat rx = ux(roi), ry = uy(roi);
    relax(rx, field.dx()(roi), ry, field.dy()(roi), held, sweeps, relaxation);
    return {ux, uy, field.cellPx()};
}

} // namespace slicestation::pipeline
