#include "slicestation/pipeline/medial_axis.hpp"

#include <CGAL/Constrained_Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Triangulation_face_base_with_info_2.h>
#include <CGAL/Triangulation_vertex_base_with_info_2.h>

#include <algorithm>
#include <deque>
#include <limits>
#include <map>
#include <set>

namespace slicestation::pipeline {
namespace {

using K = CGAL::Exact_predicates_inexact_constructions_kernel;
struct FaceInfo {
    int nesting = -1; ///< number of outline edges crossed from the infinite face
    int node = -1;    ///< index among kept exterior faces
};
using Vb = CGAL::Triangulation_vertex_base_with_info_2<int, K>;
using Fbi = CGAL::Triangulation_face_base_with_info_2<FaceInfo, K>;
using Fb = CGAL::Constrained_triangulation_face_base_2<K, Fbi>;
using Tds = CGAL::Triangulation_data_structure_2<Vb, Fb>;
// Exact intersection handling: an outline from a pixel mask may touch itself at one pixel.
using Cdt = CGAL::Constrained_Delaunay_triangulation_2<K, Tds, CGAL::Exact_predicates_tag>;

/// Flood fill over faces; crossing a constrained edge raises the nesting level by one.
void markNesting(Cdt& cdt) {
    for (auto f = cdt.all_faces_begin(); f != cdt.all_faces_end(); ++f)
        f->info().nesting = -1;
    std::deque<std::pair<Cdt::Face_handle, int>> border{{cdt.infinite_face(), 0}};
    while (!border.empty()) {
        auto [start, level] = border.front();
        border.pop_front();
        if (start->info().nesting != -1)
            continue;
        std::deque<Cdt::Face_handle> queue{start};
        start->info().nesting = level;
        while (!queue.empty()) {
            const Cdt::Face_handle f = queue.front();
            queue.pop_front();
            for (int i = 0; i < 3; ++i) {
                const Cdt::Face_handle n = f->neighbor(i);
                if (n->info().nesting != -1)
                    continue;
                if (cdt.is_constrained(Cdt::Edge(f, i))) {
                    border.emplace_back(n, level + 1);
                } else {
                    n->info().nesting = level;
                    queue.push_back(n);
                }
            }
        }
    }
}

/// Longest path in a forest piece (a tree after Voronoi duality; cycles around holes in the
/// exterior are harmless: the search takes the farthest node twice, which bounds the length).
double longestPath(const std::vector<std::vector<std::pair<int, double>>>& adj,
                   const std::vector<int>& nodes) {
    auto farthest = [&](int from) {
        std::map<int, double> dist{{from, 0.0}};
        std::deque<int> q{from};
        int far = from;
        while (!q.empty()) {
            const int u = q.front();
            q.pop_front();
            for (const auto& [v, w] : adj[u]) {
                if (dist.count(v))
                    continue;
                dist[v] = dist[u] + w;
                if (dist[v] > dist[far])
                    far = v;
                q.push_back(v);
            }
        }
        return std::pair<int, double>{far, dist[far]};
    };
    if (nodes.empty())
        return 0;
    const int a = farthest(nodes.front()).first;
    return farthest(a).second;
}

} // namespace

ExteriorTriangulation exteriorMedialAxis(const std::vector<cv::Point2f>& outline) {
    ExteriorTriangulation out;
    if (outline.size() < 3)
        return out;
    Cdt cdt;
    std::vector<Cdt::Vertex_handle> vh;
    vh.reserve(outline.size());
    for (size_t i = 0; i < outline.size(); ++i) {
        auto v = cdt.insert(K::Point_2(outline[i].x, outline[i].y));
        v->info() = static_cast<int>(i);
        vh.push_back(v);
    }
    for (size_t i = 0; i < vh.size(); ++i) {
        const auto& a = vh[i];
        const auto& b = vh[(i + 1) % vh.size()];
        if (a != b)
            cdt.insert_constraint(a, b);
    }
    // Vertices the triangulation created where the outline touches itself belong to no outline
    // index; duplicates of one point keep the first index.
    std::set<Cdt::Vertex_handle> ours(vh.begin(), vh.end());
    for (auto v = cdt.finite_vertices_begin(); v != cdt.finite_vertices_end(); ++v)
        if (!ours.count(v))
            v->info() = -1;
    markNesting(cdt);

    // Kept exterior faces: even nesting, finite, circumcentre inside (non-obtuse): Algorithm 2
    // line 2 drops the skinny ones.
    std::vector<Cdt::Face_handle> kept;
    std::vector<cv::Point2d> centre;
    for (auto f = cdt.finite_faces_begin(); f != cdt.finite_faces_end(); ++f) {
        if (f->info().nesting % 2 == 1) {
            ++out.insideFaces;
            continue;
        }
        ++out.exteriorFaces;
        const K::Triangle_2 tri = cdt.triangle(f);
        const K::Point_2 c = CGAL::circumcenter(tri);
        cv::Point2d node(CGAL::to_double(c.x()), CGAL::to_double(c.y()));
        if (tri.bounded_side(c) == CGAL::ON_UNBOUNDED_SIDE) {
            // A skinny triangle's circumcentre lies outside it (Algorithm 2, line 2 drops it).
            // Dropping it outright also cuts the axis of a straight-sided wedge into pieces,
            // where such triangles alternate with good ones, so it stays as a joint placed at
            // the middle of its longest edge, where its circumcentre projects.
            int longest = 0;
            double best = -1;
            for (int i = 0; i < 3; ++i) {
                const double len = CGAL::to_double(
                    CGAL::squared_distance(tri.vertex((i + 1) % 3), tri.vertex((i + 2) % 3)));
                if (len > best) {
                    best = len;
                    longest = i;
                }
            }
            const K::Point_2 m =
                CGAL::midpoint(tri.vertex((longest + 1) % 3), tri.vertex((longest + 2) % 3));
            node = {CGAL::to_double(m.x()), CGAL::to_double(m.y())};
        } else {
            ++out.keptFaces;
        }
        f->info().node = static_cast<int>(kept.size());
        kept.push_back(f);
        centre.push_back(node);
    }

    // Voronoi edges between kept neighbours across edges that are not outline edges (line 3).
    std::vector<std::vector<std::pair<int, double>>> adj(kept.size());
    for (size_t k = 0; k < kept.size(); ++k) {
        for (int i = 0; i < 3; ++i) {
            const Cdt::Face_handle n = kept[k]->neighbor(i);
            const int m = n->info().node;
            if (m < 0 || m <= static_cast<int>(k) || cdt.is_infinite(n))
                continue;
            if (cdt.is_constrained(Cdt::Edge(kept[k], i)))
                continue;
            const double w = cv::norm(centre[k] - centre[m]);
            adj[k].emplace_back(m, w);
            adj[m].emplace_back(static_cast<int>(k), w);
        }
    }
    // Connected pieces (line 4 keeps those whose length reaches alpha; the caller decides).
    std::vector<int> comp(kept.size(), -1);
    for (size_t s = 0; s < kept.size(); ++s) {
        if (comp[s] >= 0)
            continue;
        std::vector<int> nodes;
        std::deque<int> q{static_cast<int>(s)};
        comp[s] = static_cast<int>(out.branches.size());
        while (!q.empty()) {
            const int u = q.front();
            q.pop_front();
            nodes.push_back(u);
            for (const auto& [v, w] : adj[u]) {
                if (comp[v] >= 0)
                    continue;
                comp[v] = comp[s];
                q.push_back(v);
            }
        }
        MedialBranch b;
        b.length = longestPath(adj, nodes);
        std::set<int> verts;
        for (int u : nodes) {
            b.axis.push_back(centre[u]);
            for (int i = 0; i < 3; ++i) {
                const int vi = kept[u]->vertex(i)->info();
                if (vi >= 0 && vi < static_cast<int>(outline.size()))
                    verts.insert(vi);
            }
        }
        b.outlineVertices.assign(verts.begin(), verts.end());
        out.branches.push_back(std::move(b));
    }
    std::sort(out.branches.begin(), out.branches.end(),
              [](const MedialBranch& a, const MedialBranch& b) { return a.length > b.length; });
    return out;
}

} // namespace slicestation::pipeline
