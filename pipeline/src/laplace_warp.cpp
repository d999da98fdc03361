#include "slicestation/pipeline/laplace_warp.hpp"

#include "side_by_side.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>

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
/// chain of dependent updates; to keep the processor busy, two rows are updated at a time, the
/// lower one a node behind (a wavefront): every node still reads exactly the values it reads in
/// plain row order (its left and upper neighbours updated, its right and lower ones not yet), so
/// the result is the same to the bit.
void relaxOne(cv::Mat& u, const cv::Mat& fixed, const cv::Mat& isFixed, int sweeps, double w) {
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
    // The same update away from the borders, on row pointers (no mirror indices to work out):
    // the same sums in the same order, so the same bits.
    const auto inner = [wf](const float* up, float* row, const float* down, const uchar* held,
                            const float* value, int j) {
        if (held[j]) {
            row[j] = value[j];
            return;
        }
        const float avg = 0.25f * (row[j - 1] + row[j + 1] + up[j] + down[j]);
        row[j] += wf * (avg - row[j]);
    };
    for (int s = 0; s < sweeps; ++s) {
        int i = 0;
        for (; i + 1 < rows; i += 2) {
            // Row i and row i + 1 are interior when both their neighbours are inside the grid
            // (row i + 1 always is below row i).
            const bool innerA = i >= 1, innerB = i + 2 < rows;
            float* ra = u.ptr<float>(i);
            float* rb = u.ptr<float>(i + 1);
            const float* ua = innerA ? u.ptr<float>(i - 1) : nullptr;
            const float* db = innerB ? u.ptr<float>(i + 2) : nullptr;
            const uchar* ha = isFixed.ptr<uchar>(i);
            const uchar* hb = isFixed.ptr<uchar>(i + 1);
            const float* va = fixed.ptr<float>(i);
            const float* vb = fixed.ptr<float>(i + 1);
            update(i, 0);
            for (int j = 1; j < cols; ++j) {
                if (innerA && j + 1 < cols)
                    inner(ua, ra, rb, ha, va, j);
                else
                    update(i, j);
                if (innerB && j - 1 >= 1)
                    inner(ra, rb, db, hb, vb, j - 1);
                else
                    update(i + 1, j - 1);
            }
            update(i + 1, cols - 1);
        }
        for (; i < rows; ++i)
            for (int j = 0; j < cols; ++j)
                update(i, j);
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
