#include "slicestation/daemon/config/scan_plan.hpp"

#include "slicestation/daemon/config/config_document.hpp"

#include <cmath>
#include <set>
#include <sstream>

namespace slicestation::daemon {

using core::Result;

namespace {

Result<void> checkName(const std::string& name, const FieldReader& rd, const std::string& field) {
    if (name.empty())
        return rd.bad(field, "must not be empty");
    if (name.size() > kMaxPlanNameBytes)
        return rd.bad(field, std::to_string(name.size()) + " bytes is longer than the " +
                                 std::to_string(kMaxPlanNameBytes) + " a name may have");
    for (const char c : name) {
        const auto u = static_cast<unsigned char>(c);
        if (u < 0x20 || u == 0x7f)
            return rd.bad(field, "must not contain control characters");
        if (c == '/' || c == '\\')
            return rd.bad(field, "must not contain '/' or '\\'");
    }
    if (name.find_first_not_of('.') == std::string::npos)
        return rd.bad(field, "must not be only dots");
    return {};
}

/// The plan's `name`: 1..kMaxRunNameBytes bytes, no control characters.
Result<std::string> readRunName(const nlohmann::json& doc, const FieldReader& rd) {
    auto name = rd.string(doc, "", "name", std::nullopt);
    if (!name)
        return name.error();
    if (name->empty())
        return rd.bad("name", "must not be empty");
    if (name->size() > kMaxRunNameBytes)
        return rd.bad("name", std::to_string(name->size()) + " bytes is longer than the " +
                                  std::to_string(kMaxRunNameBytes) + " a run name may have");
    for (const char c : *name)
        if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f)
            return rd.bad("name", "must not contain control characters");
    return *name;
}

/// A slide table's keys and name (default "slide-<n>").
Result<std::string> readSlideName(const nlohmann::json& slide, const std::string& sp,
                                  std::size_t si, const FieldReader& rd) {
    if (!slide.is_object())
        return rd.bad(sp, "expected a table/object");
    if (auto k = rd.onlyKeys(slide, sp, {"name", "sections"}); !k)
        return k.error();
    auto slideName = rd.string(slide, sp, "name", "slide-" + std::to_string(si + 1));
    if (!slideName)
        return slideName.error();
    if (auto c = checkName(*slideName, rd, sp + ".name"); !c)
        return c.error();
    return *slideName;
}

} // namespace

Result<ScanPlan> parseScanPlan(const nlohmann::json& doc, const std::string& origin) {
    FieldReader rd(origin);
    if (!doc.is_object())
        return rd.bad("(document)", "expected a table/object at the top");
    if (auto k = rd.onlyKeys(doc, "(document)", {"name", "slides"}); !k)
        return k.error();
    ScanPlan plan;
    plan.document = doc;
    auto name = readRunName(doc, rd);
    if (!name)
        return name.error();
    plan.name = *name;
    if (!doc.contains("slides"))
        return rd.bad("slides", "missing (a plan needs at least one slide)");
    const auto& slides = doc["slides"];
    if (!slides.is_array() || slides.empty())
        return rd.bad("slides", "expected a non-empty array of slides");
    std::set<std::string> names;
    for (std::size_t si = 0; si < slides.size(); ++si) {
        const std::string sp = "slides[" + std::to_string(si) + "]";
        const auto& slide = slides[si];
        auto slideName = readSlideName(slide, sp, si, rd);
        if (!slideName)
            return slideName.error();
        if (!slide.contains("sections") || !slide["sections"].is_array() ||
            slide["sections"].empty())
            return rd.bad(sp + ".sections", "expected a non-empty array of sections");
        const auto& secs = slide["sections"];
        for (std::size_t k = 0; k < secs.size(); ++k) {
            const std::string p = sp + ".sections[" + std::to_string(k) + "]";
            const auto& s = secs[k];
            if (!s.is_object())
                return rd.bad(p, "expected a table/object");
            if (auto key = rd.onlyKeys(s, p,
                                       {"name", "x_um", "y_um", "width_um", "height_um",
                                        "atlas_slice", "atlas_position_um"});
                !key)
                return key.error();
            if (plan.sections.size() >= kMaxPlanSections)
                return rd.bad(p, "a plan may have at most " + std::to_string(kMaxPlanSections) +
                                     " sections");
            PlanSection ps;
            auto& sec = ps.section;
            sec.slideIndex = static_cast<int>(si);
            sec.slideName = *slideName;
            sec.index = static_cast<int>(k);
            auto nm =
                rd.string(s, p, "name", "s" + std::to_string(si + 1) + "-" + std::to_string(k + 1));
            if (!nm)
                return nm.error();
            if (auto c = checkName(*nm, rd, p + ".name"); !c)
                return c.error();
            sec.name = *nm;
            if (!names.insert(sec.slideName + "/" + sec.name).second)
                return rd.bad(p + ".name",
                              "\"" + sec.name + "\" appears twice on " + sec.slideName);
            auto x =
                rd.number(s, p, "x_um", std::nullopt, -kMaxPlanCoordinateUm, kMaxPlanCoordinateUm);
            if (!x)
                return x.error();
            auto y =
                rd.number(s, p, "y_um", std::nullopt, -kMaxPlanCoordinateUm, kMaxPlanCoordinateUm);
            if (!y)
                return y.error();
            auto w = rd.number(s, p, "width_um", 0.0, 0.0, 1e6);
            if (!w)
                return w.error();
            auto h = rd.number(s, p, "height_um", 0.0, 0.0, 1e6);
            if (!h)
                return h.error();
            sec.xUm = *x;
            sec.yUm = *y;
            sec.widthUm = *w;
            sec.heightUm = *h;
            const bool hasSlice = s.contains("atlas_slice");
            const bool hasPos = s.contains("atlas_position_um");
            if (hasSlice && hasPos)
                return rd.bad(p, "give atlas_slice or atlas_position_um, not both");
            if (hasSlice) {
                auto i = rd.integer(s, p, "atlas_slice", std::nullopt, 0, 100'000);
                if (!i)
                    return i.error();
                sec.expectedSlice = static_cast<int>(*i);
            } else if (hasPos) {
                auto pos = rd.number(s, p, "atlas_position_um", std::nullopt, -kMaxPlanCoordinateUm,
                                     kMaxPlanCoordinateUm);
                if (!pos)
                    return pos.error();
                ps.atlasPositionUm = *pos;
            }
            plan.sections.push_back(std::move(ps));
        }
    }
    return plan;
}

Result<void> resolveScanPlan(ScanPlan& plan, const hw::StageLimits& limits,
                             const std::vector<double>& slicePositionsUm,
                             const std::string& origin) {
    FieldReader rd(origin);
    for (auto& ps : plan.sections) {
        auto& s = ps.section;
        const std::string p = "slides[" + std::to_string(s.slideIndex) + "].sections[" +
                              std::to_string(s.index) + "]";
        // The whole extent, not only the centre: a tile outside the soft limits would pause the
        // run at scan time, long after the plan was accepted.

        const auto inside = [&](const hw::AxisRange& r, double centre, double size,
                                const char* axis, const char* key,
                                const char* sizeKey) -> Result<void> {
            const double lo = centre - size / 2, hi = centre + size / 2;
            if (lo >= r.minUm && hi <= r.maxUm)
                return {};
            std::ostringstream os;
            os << "section \"" << s.name << "\" on " << s.slideName << " reaches " << axis << " "
               << lo << " .. " << hi << " um (" << key << " +- " << sizeKey
               << "/2), outside the stage's " << axis << " limits [" << r.minUm << ", " << r.maxUm
               << "] um";
            return rd.bad(p + "." + key, os.str());
        };
        if (auto r = inside(limits.x, s.xUm, s.widthUm, "X", "x_um", "width_um"); !r)
            return r.error();
        if (auto r = inside(limits.y, s.yUm, s.heightUm, "Y", "y_um", "height_um"); !r)
            return r.error();
        if (ps.atlasPositionUm) {
            if (slicePositionsUm.empty())
                return rd.bad(p + ".atlas_position_um", "the atlas stack is empty");
            std::size_t best = 0;
            for (std::size_t i = 1; i < slicePositionsUm.size(); ++i)
                if (std::abs(slicePositionsUm[i] - *ps.atlasPositionUm) <
                    std::abs(slicePositionsUm[best] - *ps.atlasPositionUm))
                    best = i;
            const double spacing = slicePositionsUm.size() > 1
                                       ? std::abs(slicePositionsUm[1] - slicePositionsUm[0])
                                       : 0.0;
            if (std::abs(slicePositionsUm[best] - *ps.atlasPositionUm) > std::max(spacing, 1.0))
                return rd.bad(p + ".atlas_position_um",
                              std::to_string(*ps.atlasPositionUm) +
                                  " um lies outside the atlas stack (" +
                                  std::to_string(slicePositionsUm.front()) + " .. " +
                                  std::to_string(slicePositionsUm.back()) + " um)");
            s.expectedSlice = static_cast<int>(best);
        } else if (s.expectedSlice) {
            if (*s.expectedSlice >= static_cast<int>(slicePositionsUm.size()))
                return rd.bad(p + ".atlas_slice", std::to_string(*s.expectedSlice) +
                                                      " is not in the atlas stack (slices 0.." +
                                                      std::to_string(slicePositionsUm.size() - 1) +
                                                      ")");
        }
    }
    return {};
}

} // namespace slicestation::daemon
