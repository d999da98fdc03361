#pragma once
/// The series as context of the damage decision (issue 18, item 5; docs/damage.md, "The series
/// as context"). Sections of one brain arrive in order; anatomy that looks like damage (a
/// ventricle wider than the atlas's, a fissure opened) persists over neighbouring sections, a
/// tear does not. Each registered section is judged again with what the sections of its run
/// registered before it show in atlas px: their gaps, and their glass where their atlas expects
/// tissue (pipeline::judgeInSeries, pipeline::shownInSeries).
///
/// The context lives in the journal, not in memory: every registration's result document keeps
/// its gaps and that glass in atlas pixels ("damage_atlas", "glass_atlas"), and the earlier
/// sections' latest registrations are read back, so a restart loses nothing. The slices of one
/// atlas stack share one pixel grid, so atlas px of two sections registered to different slices
/// compare places.
///
/// Threading: call from the registration worker's thread (the journal is thread-safe).
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/daemon/storage/journal.hpp"
#include "slicestation/pipeline/damage_series.hpp"

#include <nlohmann/json.hpp>

#include <cstdint>
#include <vector>

namespace slicestation::daemon {

/// The gaps' outlines as result.json keeps them: one array of [x, y] (atlas px) per damage
/// region, parallel to "damage_regions" (empty for fragments and folds).
nlohmann::json atlasOutlinesJson(const pipeline::AtlasDamageOutlines& outlines);
/// Reads the outlines under `key` ("damage_atlas", "glass_atlas") of a result document back;
/// empty when it has none (registrations journalled before the series context, or before the
/// glass was kept) or it is malformed.
pipeline::AtlasDamageOutlines atlasOutlinesFromResult(const nlohmann::json& result,
                                                      const char* key = "damage_atlas");

/// What the sections of run `runId` registered before section `sectionId` show as context
/// (pipeline::SectionShown: each one's "damage_atlas" and "glass_atlas"):
/// walking back in the plan's order from it, the latest registration of each earlier section
/// that has one (pending and failed ones are passed over), nearest first, at most `window`
/// (pipeline::SeriesContextParams::window, 2).
/// A journal error gives what was read up to it.
std::vector<pipeline::SectionShown>
earlierDamageOutlines(Journal& journal, std::int64_t runId, std::int64_t sectionId,
                      int window = pipeline::SeriesContextParams{}.window);

/// Judges `section` again with `earlier` (pipeline::judgeInSeries with the default damage
/// parameters, as registerSectionFiles uses) and updates its document: "damaged",
/// "damage_score", "damage_verdict", each region's "score" and "persistence", the gaps and the
/// glass where the atlas expects tissue in atlas px ("damage_atlas", "glass_atlas") and
/// "damage_context" (the earlier sections used, the score and verdict without them).
void judgeWithSeriesContext(RegisteredSection& section,
                            const std::vector<pipeline::SectionShown>& earlier,
                            const pipeline::SeriesContextParams& params = {});

} // namespace slicestation::daemon
