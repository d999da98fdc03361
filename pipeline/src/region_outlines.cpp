#include "slicestation/pipeline/region_outlines.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <map>
#include <unordered_map>
#include <utility>

namespace slicestation::pipeline {

cv::Mat atlasSideMap(const cv::Mat& mx, const cv::Mat& my, const SliceGeometry& slice,
                     double midlineLrUm) {
    // LR of atlas pixel (c, r): origin + c column + r row, third component.
    const double o = slice.originUm[2], c = slice.columnUm[2], r = slice.rowUm[2];
    cv::Mat lr = o + c * mx + r * my;
    cv::Mat side = lr >= midlineLrUm;
    return side / 255;
}

namespace {

struct Box {
    int x0 = INT32_MAX, y0 = INT32_MAX, x1 = -1, y1 = -1;
    std::int64_t n = 0;
};

/// A directed pixel edge between lattice corners (corner (x, y) is the top-left corner of pixel
/// (x, y)); the piece's pixel lies on its right (y down). Directions: 0 right, 1 down, 2 left,
/// 3 up.
struct Edge {
    int x, y, dir;
};

constexpr int kDx[4] = {1, 0, -1, 0};
constexpr int kDy[4] = {0, 1, 0, -1};

std::int64_t key(int x, int y) {
    return (std::int64_t(y) << 32) ^ std::uint32_t(x);
}

double signedArea(const std::vector<cv::Point>& ring) {
    double a = 0;
    for (std::size_t i = 0; i < ring.size(); ++i) {
        const cv::Point& p = ring[i];
        const cv::Point& q = ring[(i + 1) % ring.size()];
        a += double(p.x) * q.y - double(q.x) * p.y;
    }
    return a / 2;
}

bool inside(const std::vector<cv::Point>& ring, double px, double py) {
    bool in = false;
    for (std::size_t i = 0, j = ring.size() - 1; i < ring.size(); j = i++) {
        const double xi = ring[i].x, yi = ring[i].y, xj = ring[j].x, yj = ring[j].y;
        if ((yi > py) != (yj > py) && px < (xj - xi) * (py - yi) / (yj - yi) + xi)
            in = !in;
    }
    return in;
}

/// The rings of the non-zero pixels of `mask` (CV_8U, zero on its border), lattice corners.
std::vector<std::vector<cv::Point>> crackRings(const cv::Mat& mask) {
    std::vector<Edge> edges;
    for (int y = 1; y < mask.rows - 1; ++y) {
        const auto* row = mask.ptr<std::uint8_t>(y);
        const auto* up = mask.ptr<std::uint8_t>(y - 1);
        const auto* down = mask.ptr<std::uint8_t>(y + 1);
        for (int x = 1; x < mask.cols - 1; ++x) {
            if (!row[x])
                continue;
            if (!up[x])
                edges.push_back({x, y, 0});
            if (!row[x + 1])
                edges.push_back({x + 1, y, 1});
            if (!down[x])
                edges.push_back({x + 1, y + 1, 2});
            if (!row[x - 1])
                edges.push_back({x, y + 1, 3});
        }
    }
    std::unordered_map<std::int64_t, std::vector<int>> from;
    from.reserve(edges.size());
    for (int i = 0; i < int(edges.size()); ++i)
        from[key(edges[std::size_t(i)].x, edges[std::size_t(i)].y)].push_back(i);
    std::vector<char> used(edges.size(), 0);
    std::vector<std::vector<cv::Point>> rings;
    for (int start = 0; start < int(edges.size()); ++start) {
        if (used[std::size_t(start)])
            continue;
        std::vector<cv::Point> ring;
        int e = start;
        while (!used[std::size_t(e)]) {
            used[std::size_t(e)] = 1;
            const Edge& ed = edges[std::size_t(e)];
            ring.push_back({ed.x, ed.y}); // collinear points are dropped below
            const int ex = ed.x + kDx[ed.dir], ey = ed.y + kDy[ed.dir];
            const auto& out = from[key(ex, ey)];
            // At a corner shared by diagonal pixels: turn right (around the pixel on our right),
            // so the piece's pixels are 4-connected and rings never cross.
            int next = -1, best = 4;
            for (int c : out) {
                if (used[std::size_t(c)] && c != start)
                    continue;
                const int turn = (edges[std::size_t(c)].dir - ed.dir + 4) % 4; // 1 right, 0, 3
                const int rank = turn == 1 ? 0 : turn == 0 ? 1 : 2;
                if (rank < best) {
                    best = rank;
                    next = c;
                }
            }
            if (next < 0 || next == start)
                break;
            e = next;
        }
        // Drop collinear points.
        std::vector<cv::Point> corners;
        for (std::size_t i = 0; i < ring.size(); ++i) {
            const cv::Point& a = ring[(i + ring.size() - 1) % ring.size()];
            const cv::Point& b = ring[i];
            const cv::Point& c = ring[(i + 1) % ring.size()];
            if ((b - a).cross(c - b) != 0)
                corners.push_back(b);
        }
        if (corners.size() >= 4)
            rings.push_back(std::move(corners));
    }
    return rings;
}

} // namespace

std::vector<RegionOutline> regionOutlines(const cv::Mat& labels, const cv::Mat& side,
                                          int minPiecePx) {
    CV_Assert(labels.type() == CV_32S);
    CV_Assert(side.empty() || (side.type() == CV_8U && side.size() == labels.size()));
    // One pass for the bounding box of every (id, side), so each region is traced in its box
    // only: a full-ontology section has hundreds of regions.
    std::map<std::pair<std::int32_t, int>, Box> boxes;
    for (int y = 0; y < labels.rows; ++y) {
        const auto* l = labels.ptr<std::int32_t>(y);
        const auto* s = side.empty() ? nullptr : side.ptr<std::uint8_t>(y);
        for (int x = 0; x < labels.cols; ++x) {
            if (l[x] == 0)
                continue;
            Box& b = boxes[{l[x], s ? int(s[x]) : 0}];
            b.x0 = std::min(b.x0, x);
            b.x1 = std::max(b.x1, x);
            b.y0 = std::min(b.y0, y);
            b.y1 = std::max(b.y1, y);
            ++b.n;
        }
    }
    std::vector<RegionOutline> out;
    out.reserve(boxes.size());
    for (const auto& [id, b] : boxes) {
        RegionOutline region{id.first, id.second, b.n, {}};
        // A one-pixel margin of zeros around the box.
        const cv::Rect roi(b.x0 - 1, b.y0 - 1, b.x1 - b.x0 + 3, b.y1 - b.y0 + 3);
        const cv::Rect in = roi & cv::Rect(0, 0, labels.cols, labels.rows);
        cv::Mat mask = cv::Mat::zeros(roi.size(), CV_8U);
        cv::Mat sub = mask(in - roi.tl());
        sub = labels(in) == id.first;
        if (!side.empty())
            sub &= side(in) == id.second;
        std::vector<std::vector<cv::Point>> outers, holes;
        std::vector<double> outerArea;
        for (auto& r : crackRings(mask)) {
            const double a = signedArea(r);
            if (a > 0) {
                outerArea.push_back(a);
                outers.push_back(std::move(r));
            } else {
                holes.push_back(std::move(r));
            }
        }
        std::vector<OutlinePiece> pieces(outers.size());
        for (const auto& h : holes) {
            // A point just inside the hole: the first edge's middle, a quarter pixel to its left
            // (the hole's side), never on a lattice line.
            const cv::Point d = h[1] - h[0];
            const double len = std::hypot(d.x, d.y);
            const double px = h[0].x + 0.5 * d.x / len + 0.25 * d.y / len;
            const double py = h[0].y + 0.5 * d.y / len - 0.25 * d.x / len;
            int owner = -1;
            for (std::size_t k = 0; k < outers.size(); ++k)
                if ((owner < 0 || outerArea[k] < outerArea[std::size_t(owner)]) &&
                    inside(outers[k], px, py))
                    owner = int(k);
            if (owner < 0)
                continue;
            std::vector<cv::Point2d> ring;
            for (const cv::Point& p : h)
                ring.push_back({p.x + roi.x - 0.5, p.y + roi.y - 0.5});
            pieces[std::size_t(owner)].holes.push_back(std::move(ring));
            pieces[std::size_t(owner)].areaPx += signedArea(h); // negative
        }
        for (std::size_t k = 0; k < outers.size(); ++k) {
            OutlinePiece& p = pieces[k];
            for (const cv::Point& q : outers[k])
                p.outer.push_back({q.x + roi.x - 0.5, q.y + roi.y - 0.5});
            p.areaPx += outerArea[k];
            if (p.areaPx >= minPiecePx)
                region.pieces.push_back(std::move(p));
        }
        out.push_back(std::move(region));
    }
    return out;
}

} // namespace slicestation::pipeline
