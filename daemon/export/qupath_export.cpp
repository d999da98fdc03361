// QuPath: the atlas regions of a section as a GeoJSON FeatureCollection (docs/results.md).
#include "slicestation/daemon/export/section_export.hpp"

#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/region_outlines.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <map>

namespace slicestation::daemon {

using nlohmann::json;

// --- QuPath ------------------------------------------------------------------------------------

namespace {

json ring(const std::vector<cv::Point2d>& pts) {
    json r = json::array();
    for (const cv::Point2d& p : pts)
        r.push_back({p.x + 0.5, p.y + 0.5}); // QuPath: from the corner (pixel centres at +0.5)
    if (!pts.empty())
        r.push_back({pts.front().x + 0.5, pts.front().y + 0.5});
    return r;
}

json rgb(std::uint32_t c) {
    return {(c >> 16) & 255u, (c >> 8) & 255u, c & 255u};
}

} // namespace

json qupathFeatures(const cv::Mat& labels, const cv::Mat& side, const RegionLookup& regions,
                    const json& damageRegions) {
    json features = json::array();
    for (const pipeline::RegionOutline& r : pipeline::regionOutlines(labels, side)) {
        if (r.pieces.empty())
            continue;
        json polys = json::array();
        for (const pipeline::OutlinePiece& p : r.pieces) {
            json poly = json::array({ring(p.outer)});
            for (const auto& h : p.holes)
                if (h.size() >= 3)
                    poly.push_back(ring(h));
            polys.push_back(std::move(poly));
        }
        const StackRegion* info = regions ? regions(std::uint32_t(r.id)) : nullptr;
        const std::string acronym =
            info && !info->acronym.empty() ? info->acronym : std::to_string(r.id);
        const std::string name = info && !info->name.empty() ? info->name : acronym;
        const std::string hemisphere = side.empty() ? "" : (r.side ? "right" : "left");
        json props{{"objectType", "annotation"},
                   {"name", hemisphere.empty() ? name : name + " (" + hemisphere + ")"},
                   {"classification",
                    {{"name", acronym}, {"color", rgb(info ? info->colorRgb : 0x808080u)}}},
                   {"allen_id", r.id},
                   {"acronym", acronym},
                   {"region_name", name},
                   {"area_px", r.pixels},
                   {"isLocked", true}};
        if (!hemisphere.empty())
            props["hemisphere"] = hemisphere;
        if (info && info->path.size() >= 1) {
            // The full Allen hierarchy: roll a region up to any ancestor.
            props["structure_id_path"] = info->path;
            if (info->path.size() >= 2)
                props["parent_id"] = info->path[info->path.size() - 2];
        }
        json geometry = polys.size() == 1 ? json{{"type", "Polygon"}, {"coordinates", polys[0]}}
                                          : json{{"type", "MultiPolygon"}, {"coordinates", polys}};
        features.push_back(
            {{"type", "Feature"}, {"geometry", std::move(geometry)}, {"properties", props}});
    }
    if (damageRegions.is_array())
        for (const json& d : damageRegions) {
            if (!d.is_object() || !d.contains("polygon") || !d["polygon"].is_array() ||
                d["polygon"].size() < 3)
                continue;
            json r = json::array();
            for (const json& p : d["polygon"])
                if (p.is_array() && p.size() == 2 && p[0].is_number() && p[1].is_number())
                    r.push_back({p[0].get<double>() + 0.5, p[1].get<double>() + 0.5});
            if (r.size() < 3)
                continue;
            r.push_back(r[0]);
            features.push_back(
                {{"type", "Feature"},
                 {"geometry", {{"type", "Polygon"}, {"coordinates", json::array({r})}}},
                 {"properties",
                  {{"objectType", "annotation"},
                   {"name", "Damage (" + d.value("kind", std::string("damage")) + ")"},
                   {"classification", {{"name", "Damage"}, {"color", {255, 0, 0}}}},
                   {"damage_kind", d.value("kind", std::string())},
                   {"area_px", d.value("area_px", 0.0)},
                   {"score", d.value("score", 0.0)}}}});
        }
    return {{"type", "FeatureCollection"}, {"features", std::move(features)}};
}

} // namespace slicestation::daemon
