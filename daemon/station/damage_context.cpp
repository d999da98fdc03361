#include "slicestation/daemon/station/damage_context.hpp"

#include <algorithm>
#include <string>

namespace slicestation::daemon {

nlohmann::json atlasOutlinesJson(const pipeline::AtlasDamageOutlines& outlines) {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& polygon : outlines) {
        nlohmann::json p = nlohmann::json::array();
        for (const cv::Point2f& v : polygon)
            p.push_back({v.x, v.y});
        out.push_back(std::move(p));
    }
    return out;
}

pipeline::AtlasDamageOutlines atlasOutlinesFromResult(const nlohmann::json& result,
                                                      const char* key) {
    pipeline::AtlasDamageOutlines out;
    const auto it = result.find(key);
    if (it == result.end() || !it->is_array())
        return out;
    for (const nlohmann::json& p : *it) {
        std::vector<cv::Point2f> polygon;
        if (p.is_array())
            for (const nlohmann::json& v : p)
                if (v.is_array() && v.size() == 2 && v[0].is_number() && v[1].is_number())
                    polygon.emplace_back(v[0].get<float>(), v[1].get<float>());
        out.push_back(std::move(polygon));
    }
    return out;
}

std::vector<pipeline::SectionShown> earlierDamageOutlines(Journal& journal, std::int64_t runId,
                                                          std::int64_t sectionId, int window) {
    std::vector<pipeline::SectionShown> out;
    auto sections = journal.sections(runId);
    if (!sections)
        return out;
    std::size_t at = 0;
    while (at < sections->size() && (*sections)[at].id != sectionId)
        ++at;
    // The sections before it in the plan's order are those cut before it (and registered
    // before it, unless this is a rescan).
    for (std::size_t k = at; k > 0 && static_cast<int>(out.size()) < window; --k) {
        auto regs = journal.registrations((*sections)[k - 1].id);
        if (!regs || regs->empty())
            continue;
        const nlohmann::json& result = regs->back().result;
        out.push_back(
            {atlasOutlinesFromResult(result), atlasOutlinesFromResult(result, "glass_atlas")});
    }
    return out;
}

void judgeWithSeriesContext(RegisteredSection& section,
                            const std::vector<pipeline::SectionShown>& earlier,
                            const pipeline::SeriesContextParams& params) {
    pipeline::Registration& reg = section.registration;
    nlohmann::json& doc = section.document;
    const double aloneScore = reg.damageScore;
    const std::string aloneVerdict(pipeline::toString(reg.damageVerdict));
    pipeline::judgeInSeries(reg, earlier, pipeline::RegistrationOptions{}.damage, params);
    doc["damaged"] = reg.damaged;
    doc["damage_score"] = reg.damageScore;
    doc["damage_verdict"] = std::string(pipeline::toString(reg.damageVerdict));
    nlohmann::json& regions = doc["damage_regions"];
    for (std::size_t i = 0; i < reg.damage.size() && i < regions.size(); ++i) {
        regions[i]["score"] = reg.damage[i].score;
        regions[i]["persistence"] = reg.damage[i].persistence;
    }
    doc["damage_atlas"] = atlasOutlinesJson(pipeline::atlasDamageOutlines(reg));
    doc["glass_atlas"] = atlasOutlinesJson(reg.glassAtlas);
    doc["damage_context"] = {
        {"earlier_sections",
         std::min<std::size_t>(earlier.size(), static_cast<std::size_t>(params.window))},
        {"window", params.window},
        {"score_alone", aloneScore},
        {"verdict_alone", aloneVerdict}};
}

} // namespace slicestation::daemon
