#include "slicestation/pipeline/smooth_warp.hpp"

#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/icp.hpp"

#include <Eigen/Dense>

#include <algorithm>
#include <array>
#include <cmath>

namespace slicestation::pipeline {

namespace {

/// Uniform cubic B-spline over a domain: control point (i, j) sits at ((j - 1) h, (i - 1) h).
class BSpline {
public:
    BSpline(cv::Size domain, double spacing)
        : h_(spacing), cols_(static_cast<int>(std::floor((domain.width - 1) / spacing)) + 4),
          rows_(static_cast<int>(std::floor((domain.height - 1) / spacing)) + 4) {}

    int nodes() const { return cols_ * rows_; }
    int cols() const { return cols_; }
    int rows() const { return rows_; }

    /// The 16 control points that carry p and their weights.
    void support(cv::Point2d p, std::array<int, 16>& index, std::array<double, 16>& weight) const {
        const double u = std::max(0.0, p.x / h_), v = std::max(0.0, p.y / h_);
        const int ku = std::min(static_cast<int>(u), cols_ - 4);
        const int kv = std::min(static_cast<int>(v), rows_ - 4);
        const auto bu = basis(u - ku), bv = basis(v - kv);
        for (int a = 0; a < 4; ++a)
            for (int b = 0; b < 4; ++b) {
                index[size_t(a * 4 + b)] = (kv + a) * cols_ + (ku + b);
                weight[size_t(a * 4 + b)] = bv[size_t(a)] * bu[size_t(b)];
            }
    }

    cv::Point2d at(cv::Point2d p, const Eigen::VectorXd& c) const {
        std::array<int, 16> idx{};
        std::array<double, 16> w{};
        support(p, idx, w);
        cv::Point2d d(0, 0);
        for (size_t k = 0; k < 16; ++k) {
            d.x += w[k] * c[idx[k]];
            d.y += w[k] * c[nodes() + idx[k]];
        }
        return d;
    }

private:
    static std::array<double, 4> basis(double t) {
        t = std::clamp(t, 0.0, 1.0);
        const double t2 = t * t, t3 = t2 * t;
        return {(1 - t) * (1 - t) * (1 - t) / 6, (3 * t3 - 6 * t2 + 4) / 6,
                (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6};
    }

    double h_;
    int cols_, rows_;
};

struct Row {
    cv::Point2d p, n;
    double y = 0; ///< n . (target - affine(p)): the field's wanted normal component at p
    double weight = 1;
};

double median(std::vector<double> v) {
    if (v.empty())
        return 0;
    const auto mid = v.begin() + std::ptrdiff_t(v.size() / 2);
    std::nth_element(v.begin(), mid, v.end());
    return *mid;
}

} // namespace

DisplacementField addFields(const DisplacementField& a, const DisplacementField& b) {
    if (b.empty())
        return a;
    if (a.empty())
        return b;
    cv::Mat dx = a.dx().clone(), dy = a.dy().clone();
    for (int i = 0; i < dx.rows; ++i)
        for (int j = 0; j < dx.cols; ++j) {
            const cv::Point2d v = b.at({j * a.cellPx(), i * a.cellPx()});
            dx.at<float>(i, j) += float(v.x);
            dy.at<float>(i, j) += float(v.y);
        }
    return DisplacementField(dx, dy, a.cellPx());
}

SmoothWarp fitSmoothWarp(cv::Size domain, const cv::Matx23d& atlasFromWorking,
                         const std::vector<SmoothWarpPairing>& pairings, double cellPx,
                         const SmoothWarpOptions& options) {
    SmoothWarp out;
    if (options.levels.empty() || domain.width < 2 || domain.height < 2)
        return out;
    const BSpline spline(
        domain, std::max(4.0, options.nodeSpacing * std::max(domain.width, domain.height)));
    const int n = spline.nodes();
    Eigen::VectorXd c = Eigen::VectorXd::Zero(2 * n);
    // Membrane term: (c_p - c_q)^2 over horizontally and vertically adjacent control points.
    Eigen::MatrixXd membrane = Eigen::MatrixXd::Zero(n, n);
    auto tie = [&](int p, int q) {
        membrane(p, p) += 1;
        membrane(q, q) += 1;
        membrane(p, q) -= 1;
        membrane(q, p) -= 1;
    };
    for (int i = 0; i < spline.rows(); ++i)
        for (int j = 0; j < spline.cols(); ++j) {
            if (j + 1 < spline.cols())
                tie(i * spline.cols() + j, i * spline.cols() + j + 1);
            if (i + 1 < spline.rows())
                tie(i * spline.cols() + j, (i + 1) * spline.cols() + j);
        }

    std::vector<Row> firstRows;
    bool first = true;
    std::vector<cv::Point2f> mapped, normals;
    // Atlas px per working px, for the thinning's cells.
    const double atlasPerWorking = std::sqrt(std::abs(det(atlasFromWorking)));
    const bool thin = options.thinning > 0 && atlasPerWorking > 0;
    std::vector<EdgePoints> thinned(pairings.size());
    for (const SmoothWarpLevel& level : options.levels) {
        for (size_t k = 0; k < pairings.size(); ++k)
            if (thin && pairings[k].source)
                thinned[k] =
                    thinEdgePoints(*pairings[k].source,
                                   float(options.thinning * level.distance / atlasPerWorking));
        for (int it = 0; it < level.iterations; ++it) {
            std::vector<Row> rows;
            std::vector<double> absResidual;
            for (size_t k = 0; k < pairings.size(); ++k) {
                const SmoothWarpPairing& pairing = pairings[k];
                if (!pairing.source || !pairing.target || !pairing.targetGrid)
                    continue;
                const EdgePoints& src = thin ? thinned[k] : *pairing.source;
                mapped.clear();
                normals.clear();
                for (size_t i = 0; i < src.size(); ++i) {
                    const cv::Point2d p = src.points[i];
                    mapped.emplace_back(apply(atlasFromWorking, p) + spline.at(p, c));
                    normals.emplace_back(mapNormal(atlasFromWorking, src.normals[i]));
                }
                for (const Match& m :
                     findMatches(mapped, normals, *pairing.target, *pairing.targetGrid,
                                 level.distance, level.angleDeg, true, TargetRule::PointToLine)) {
                    const cv::Point2d p = src.points[size_t(m.source)];
                    const cv::Point2d nn = normals[size_t(m.source)];
                    const cv::Point2d mp = mapped[size_t(m.source)];
                    Row r;
                    r.p = p;
                    r.n = nn;
                    r.y = nn.dot(m.target - apply(atlasFromWorking, p));
                    r.weight = pairing.weight;
                    absResidual.push_back(std::abs(nn.dot(m.target - mp)));
                    rows.push_back(r);
                }
            }
            if (static_cast<int>(rows.size()) < options.minMatches)
                continue;
            const double sigma = std::max(0.25, 1.4826 * median(absResidual));
            const double k = options.robustK * sigma;
            // The normal equations: a row's 32 coefficients are the 16 B-spline weights times
            // n.x and times n.y, so its outer product is (w w^T) times n.x^2, n.x n.y and n.y^2.
            // Rows with the same 16 control points share one 16 x 16 block per product,
            // scattered into the system once.
            Eigen::MatrixXd A = Eigen::MatrixXd::Zero(2 * n, 2 * n);
            Eigen::VectorXd b = Eigen::VectorXd::Zero(2 * n);
            std::array<int, 16> idx{};
            std::array<double, 16> w{};
            struct Block {
                std::array<int, 16> idx{};
                Eigen::Matrix<double, 16, 16> xx = Eigen::Matrix<double, 16, 16>::Zero(),
                                              xy = Eigen::Matrix<double, 16, 16>::Zero(),
                                              yy = Eigen::Matrix<double, 16, 16>::Zero();
            };
            std::vector<int> blockOf(size_t(n), -1); // first control point -> block
            std::vector<Block> blocks;
            double totalWeight = 0;
            for (size_t r = 0; r < rows.size(); ++r) {
                const double e = absResidual[r] / k;
                const double wr = rows[r].weight / (1 + e * e);
                totalWeight += wr;
                spline.support(rows[r].p, idx, w);
                int& slot = blockOf[size_t(idx[0])];
                if (slot < 0) {
                    slot = int(blocks.size());
                    blocks.emplace_back();
                    blocks.back().idx = idx;
                }
                Block& blk = blocks[size_t(slot)];
                const Eigen::Map<const Eigen::Matrix<double, 16, 1>> wv(w.data());
                const Eigen::Matrix<double, 16, 16> ww = wv * wv.transpose();
                const double nx = rows[r].n.x, ny = rows[r].n.y;
                blk.xx.noalias() += (wr * nx * nx) * ww;
                blk.xy.noalias() += (wr * nx * ny) * ww;
                blk.yy.noalias() += (wr * ny * ny) * ww;
                for (size_t q = 0; q < 16; ++q) {
                    b[idx[q]] += wr * w[q] * nx * rows[r].y;
                    b[n + idx[q]] += wr * w[q] * ny * rows[r].y;
                }
            }
            for (const Block& blk : blocks)
                for (int a = 0; a < 16; ++a)
                    for (int q = 0; q < 16; ++q) {
                        const int i = blk.idx[size_t(a)], j = blk.idx[size_t(q)];
                        A(i, j) += blk.xx(a, q);
                        A(i, n + j) += blk.xy(a, q);
                        A(n + i, j) += blk.xy(a, q);
                        A(n + i, n + j) += blk.yy(a, q);
                    }
            const double lambda = options.stiffness * totalWeight / n;
            A.topLeftCorner(n, n) += lambda * membrane;
            A.bottomRightCorner(n, n) += lambda * membrane;
            A.diagonal().array() += 1e-6 * lambda + 1e-9;
            c = A.ldlt().solve(b);
            out.matches = static_cast<int>(rows.size());
            if (first) {
                firstRows = rows;
                double ss = 0;
                for (const double e : absResidual)
                    ss += e * e;
                out.rmsBefore = std::sqrt(ss / double(absResidual.size()));
                first = false;
            }
        }
    }
    if (firstRows.empty())
        return out;
    double ss = 0;
    for (const Row& r : firstRows) {
        const double e = r.y - r.n.dot(spline.at(r.p, c));
        ss += e * e;
    }
    out.rmsAfter = std::sqrt(ss / double(firstRows.size()));
    const int cols = static_cast<int>(std::ceil((domain.width - 1) / cellPx)) + 1;
    const int rowsN = static_cast<int>(std::ceil((domain.height - 1) / cellPx)) + 1;
    cv::Mat dx(rowsN, cols, CV_32F), dy(rowsN, cols, CV_32F);
    for (int i = 0; i < rowsN; ++i)
        for (int j = 0; j < cols; ++j) {
            const cv::Point2d v = spline.at({j * cellPx, i * cellPx}, c);
            dx.at<float>(i, j) = float(v.x);
            dy.at<float>(i, j) = float(v.y);
        }
    out.field = DisplacementField(dx, dy, cellPx);
    return out;
}

} // namespace slicestation::pipeline
