#pragma once
/// Live series matching: sections of one brain arrive one at a time, in cutting order. The first
/// few are matched against the whole stack (matchSection); after that the series model
/// (series_model.hpp) predicts where the next one lies and only the slices around the
/// prediction are searched, from a little before (a swap) to two slots after (a skip). A window
/// whose best score falls well below the series' usual score is searched again over the whole
/// stack, so a section far out of order is still found. After each section the model is fitted
/// again. `finish` re-matches the sections that ended off the line near their predicted place.
/// Pure computation; one SeriesMatcher per run, not shared between threads.

#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/series_model.hpp"

#include <vector>

namespace slicestation::pipeline {

struct SeriesMatchOptions {
    MatchOptions match;                ///< for every search (first/last bound the whole search)
    SeriesModelOptions model;          ///< intervalUm: the cutting plan's interval (0 = unknown)
    int fullSearchSections = 3;        ///< sections matched against the whole stack first
    double windowBeforeSpacings = 1.5; ///< search from this many spacings before the prediction
    double windowAfterSpacings = 2.5;  ///< to this many after (one skip and some)
    /// A windowed match scoring below this fraction of the series' median score is searched
    /// again over the whole stack; 0 never.
    double fallbackScoreRatio = 0.5;
};

/// How one section was searched.
struct SeriesSearch {
    double predictedUm = 0; ///< the model's prediction before the match (0 when none)
    bool windowed = false;  ///< only the slices [first, last] were searched
    int first = 0, last = 0;
    bool fellBack = false; ///< the window's answer was weak and the whole stack was searched
    double ms = 0;         ///< matching time
};

class SeriesMatcher {
public:
    /// `slices` must outlive the matcher.
    SeriesMatcher(const std::vector<SliceFeatures>& slices, SeriesMatchOptions options);

    /// Matches the next section and refits the model.
    /// \return the errors of matchSection (NoTissue...) and fitSeries; a failed section is not
    ///         added.
    [[nodiscard]] core::Result<SectionMatch> add(const SectionFeatures& section);

    /// Sections off the line are matched again within a spacing of the model's place for them
    /// and kept when that puts them on the line; the model is fitted once more.
    /// \return the errors of fitSeries.
    [[nodiscard]] core::Result<void> finish(const std::vector<SectionFeatures>& sections);

    const std::vector<SectionMatch>& matches() const { return matches_; }
    const std::vector<SeriesSearch>& searches() const { return searches_; }
    const SeriesFit& fit() const { return fit_; }

private:
    core::Result<void> refit();
    int indexAt(double positionUm) const;

    const std::vector<SliceFeatures>* slices_;
    SeriesMatchOptions options_;
    std::vector<SectionMatch> matches_;
    std::vector<SeriesSearch> searches_;
    SeriesFit fit_;
};

} // namespace slicestation::pipeline
