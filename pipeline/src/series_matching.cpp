#include "slicestation/pipeline/series_matching.hpp"

#include <opencv2/core.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <map>

namespace slicestation::pipeline {
namespace {

using Clock = std::chrono::steady_clock;

double msSince(Clock::time_point t) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
}

SeriesObservation observe(const SectionMatch& m) {
    SeriesObservation o;
    o.positionUm = m.positionUm;
    o.score = std::max(m.score, 0.0);
    o.tiltColumnsDeg = m.tiltColumnsDeg;
    o.tiltRowsDeg = m.tiltRowsDeg;
    o.tiltEstimated = m.tiltEstimated;
    return o;
}

double medianOf(std::vector<double> v) {
    if (v.empty())
        return 0;
    std::nth_element(v.begin(), v.begin() + long(v.size() / 2), v.end());
    return v[v.size() / 2];
}

} // namespace

SeriesMatcher::SeriesMatcher(const std::vector<SliceFeatures>& slices, SeriesMatchOptions options)
    : slices_(&slices), options_(options) {}

int SeriesMatcher::indexAt(double positionUm) const {
    // Nearest slice by position (the stack's positions increase with the index).
    const auto& s = *slices_;
    int best = 0;
    for (size_t i = 1; i < s.size(); ++i)
        if (std::abs(s[i].positionUm - positionUm) <
            std::abs(s[size_t(best)].positionUm - positionUm))
            best = int(i);
    return best;
}

core::Result<void> SeriesMatcher::refit() {
    std::vector<SeriesObservation> obs;
    for (const SectionMatch& m : matches_)
        obs.push_back(observe(m));
    auto f = fitSeries(obs, options_.model);
    if (!f)
        return f.error();
    fit_ = std::move(*f);
    return {};
}

core::Result<SectionMatch> SeriesMatcher::add(const SectionFeatures& section,
                                              const std::vector<int>& alsoScore) {
    const auto t0 = Clock::now();
    const int n = int(matches_.size());
    const int lastSlice = options_.match.last < 0 ? int(slices_->size()) - 1 : options_.match.last;
    SeriesSearch search;
    // The whole stack's search, with the slices asked for; windowed below once the model predicts.
    MatchOptions whole = options_.match;
    whole.alsoScore.insert(whole.alsoScore.end(), alsoScore.begin(), alsoScore.end());
    MatchOptions o = whole;
    const double spacing = std::abs(fit_.spacingUm);
    if (n >= options_.fullSearchSections && n > 0 && spacing > 0 && fit_.inliers >= 2) {
        search.predictedUm = fit_.predictUm(n);
        const double dir = fit_.spacingUm > 0 ? 1 : -1;
        const double a = search.predictedUm - dir * options_.windowBeforeSpacings * spacing;
        const double b = search.predictedUm + dir * options_.windowAfterSpacings * spacing;
        int first = indexAt(std::min(a, b)), last = indexAt(std::max(a, b));
        first = std::max(first, options_.match.first);
        last = std::min(last, lastSlice);
        if (last - first >= 2) {
            search.windowed = true;
            search.first = o.first = first;
            search.last = o.last = last;
        }
    }
    if (!search.windowed) {
        search.first = options_.match.first;
        search.last = lastSlice;
    }
    auto m = matchSection(section, *slices_, o);
    if (!m)
        return m.error();
    if (search.windowed && options_.fallbackScoreRatio > 0) {
        std::vector<double> scores;
        for (const SectionMatch& p : matches_)
            scores.push_back(p.score);
        if (m->score < options_.fallbackScoreRatio * medianOf(scores)) {
            auto all = matchSection(section, *slices_, whole);
            if (all && all->score > options_.fallbackGain * m->score) {
                m = std::move(all);
                search.fellBack = true;
            }
        }
    }
    search.ms = msSince(t0);
    matches_.push_back(*m);
    searches_.push_back(search);
    if (auto r = refit(); !r) {
        matches_.pop_back();
        searches_.pop_back();
        return r.error();
    }
    return m;
}

core::Result<void> SeriesMatcher::finish(const std::vector<SectionFeatures>& sections) {
    if (sections.size() != matches_.size())
        return core::makeError(core::ErrorCode::InvalidArgument,
                               "finish needs the same sections that were added, in order");
    const int lastSlice = options_.match.last < 0 ? int(slices_->size()) - 1 : options_.match.last;
    for (int pass = 0; pass < 2; ++pass) {
        const double spacing = std::abs(fit_.spacingUm);
        if (spacing <= 0 || fit_.inliers < 3)
            return {};
        const double tau = options_.model.inlierUm > 0 ? options_.model.inlierUm : 0.4 * spacing;
        const size_t n = matches_.size();
        // Moves that would make the run regular: a flagged section to the slot after its
        // on-line predecessor's or before its successor's, and for a skip the section before
        // it to the slot before its own.
        struct Move {
            size_t section;
            int slot;
        };
        std::vector<Move> moves;
        for (size_t k = 0; k < n; ++k) {
            const SeriesSectionFit& s = fit_.sections[k];
            if (s.anomaly == SeriesAnomaly::None)
                continue;
            for (size_t j = k; j-- > 0;)
                if (fit_.sections[j].inlier && fit_.sections[j].anomaly == SeriesAnomaly::None) {
                    moves.push_back({k, fit_.sections[j].slot + int(k - j)});
                    break;
                }
            for (size_t j = k + 1; j < n; ++j)
                if (fit_.sections[j].inlier && fit_.sections[j].anomaly == SeriesAnomaly::None) {
                    moves.push_back({k, fit_.sections[j].slot - int(j - k)});
                    break;
                }
            if (s.anomaly == SeriesAnomaly::Skipped && k > 0)
                moves.push_back({k - 1, s.slot - 1});
        }
        bool changed = false;
        for (const Move& mv : moves) {
            SectionMatch& current = matches_[mv.section];
            const double target = fit_.positionOfSlot(mv.slot);
            if (std::abs(current.positionUm - target) <= 0.5 * tau)
                continue;
            MatchOptions o = options_.match;
            o.first = std::max(options_.match.first, indexAt(target - 0.6 * spacing));
            o.last = std::min(lastSlice, indexAt(target + 0.6 * spacing));
            if (o.last - o.first < 2)
                continue;
            auto m = matchSection(sections[mv.section], *slices_, o);
            if (!m || std::abs(m->positionUm - target) > tau)
                continue;
            // Off the line, anything on it is better; otherwise the regular place must score
            // nearly as well as the section's own.
            const bool offLine = !fit_.sections[mv.section].inlier;
            if (offLine || m->score >= options_.regularScoreRatio * current.score) {
                current = std::move(*m);
                changed = true;
            }
        }
        if (auto r = refit(); !r)
            return r;
        if (!changed)
            break;
    }
    if (reassign())
        return refit();
    return {};
}

std::vector<size_t> chooseAlongSeries(const std::vector<std::vector<SeriesOption>>& options,
                                      double spacingUm, double weight, double cap) {
    const size_t n = options.size();
    if (n == 0 || spacingUm == 0 || !std::isfinite(spacingUm))
        return {};
    for (const auto& o : options)
        if (o.empty())
            return {};
    auto cost = [&](double a, double b) {
        const double d = (b - a) / spacingUm - 1;
        return weight * std::min(d * d, cap);
    };
    std::vector<std::vector<double>> best(n);
    std::vector<std::vector<size_t>> from(n);
    for (const SeriesOption& o : options[0])
        best[0].push_back(o.value);
    from[0].assign(options[0].size(), 0);
    for (size_t k = 1; k < n; ++k) {
        best[k].assign(options[k].size(), -1e300);
        from[k].assign(options[k].size(), 0);
        for (size_t j = 0; j < options[k].size(); ++j)
            for (size_t i = 0; i < options[k - 1].size(); ++i) {
                const double v = best[k - 1][i] + options[k][j].value -
                                 cost(options[k - 1][i].positionUm, options[k][j].positionUm);
                if (v > best[k][j]) {
                    best[k][j] = v;
                    from[k][j] = i;
                }
            }
    }
    std::vector<size_t> pick(n);
    pick[n - 1] =
        size_t(std::max_element(best[n - 1].begin(), best[n - 1].end()) - best[n - 1].begin());
    for (size_t k = n - 1; k > 0; --k)
        pick[k - 1] = from[k][pick[k]];
    return pick;
}

bool SeriesMatcher::reassign() {
    const size_t n = matches_.size();
    if (options_.orderWeight <= 0 || fit_.spacingUm == 0 || fit_.inliers < 3 || n < 3)
        return false;
    const auto& sl = *slices_;
    // Options per section: its own match (value 1, first) and, for a section the model flags
    // other than as half of a swap, every other slice it was scored against (its score over the
    // own match's). Regular sections and swapped pairs keep their own match: the score is flat
    // over neighbouring slices, so a spacing penalty on them would smooth a real swap away.
    std::vector<std::vector<SeriesOption>> opts(n);
    std::vector<std::vector<int>> indexOf(n);
    for (size_t k = 0; k < n; ++k) {
        const SectionMatch& m = matches_[k];
        const double top = std::max(m.score, 1e-12);
        opts[k].push_back({m.positionUm, 1.0});
        indexOf[k].push_back(-1);
        const SeriesAnomaly a = fit_.sections[k].anomaly;
        if (a == SeriesAnomaly::None || a == SeriesAnomaly::Swapped)
            continue;
        for (const MatchCandidate& c : m.candidates)
            if (c.index != m.index && c.index >= 0 && c.index < int(sl.size())) {
                opts[k].push_back({sl[size_t(c.index)].positionUm, std::max(0.0, c.score) / top});
                indexOf[k].push_back(c.index);
            }
    }
    const std::vector<size_t> pick =
        chooseAlongSeries(opts, fit_.spacingUm, options_.orderWeight, options_.orderCap);
    bool changed = false;
    for (size_t k = 0; k < pick.size(); ++k) {
        const int index = indexOf[k][pick[k]];
        if (index < 0)
            continue;
        SectionMatch& m = matches_[k];
        auto scoreOf = [&](int i) -> double {
            for (const MatchCandidate& c : m.candidates)
                if (c.index == i)
                    return c.score;
            return -1;
        };
        const double s = scoreOf(index);
        m.index = index;
        m.score = s;
        m.positionUm = sl[size_t(index)].positionUm;
        // Refined between the neighbouring slices as matchSection does (parabola vertex).
        const double below = scoreOf(index - 1), above = scoreOf(index + 1);
        const double den = below - 2 * s + above;
        if (below >= 0 && above >= 0 && den < 0)
            m.positionUm += std::clamp(0.5 * (below - above) / den, -0.5, 0.5) * 0.5 *
                            (sl[size_t(index + 1)].positionUm - sl[size_t(index - 1)].positionUm);
        m.tiltColumnsDeg = m.tiltRowsDeg = 0;
        m.tiltEstimated = false;
        changed = true;
    }
    return changed;
}

core::Result<TiltEstimate> searchSeriesTilt(const std::vector<SectionFeatures>& sections,
                                            const std::vector<SectionMatch>& matches,
                                            const SeriesFit& fit, const PlaneFeatures& planes,
                                            const TiltSearchOptions& options) {
    if (sections.size() != matches.size() || fit.sections.size() != matches.size())
        return core::makeError(core::ErrorCode::InvalidArgument,
                               "sections, matches and fit must describe the same series");
    if (options.sections < 1 || !(options.maxDeg > 0) || !(options.coarseStepDeg > 0) ||
        !(options.fineStepDeg > 0) || !(options.positionStepUm > 0) || options.maxDeg > 30)
        return core::makeError(core::ErrorCode::InvalidArgument,
                               "tilt search: sections >= 1, steps > 0, maxDeg in (0, 30]");
    std::vector<size_t> chosen;
    for (size_t k = 0; k < matches.size(); ++k)
        if (fit.sections[k].inlier && fit.sections[k].anomaly == SeriesAnomaly::None)
            chosen.push_back(k);
    if (chosen.size() < 2)
        return core::makeError(core::ErrorCode::InvalidArgument,
                               "tilt search needs two sections on the series' line");
    std::sort(chosen.begin(), chosen.end(),
              [&](size_t a, size_t b) { return matches[a].score > matches[b].score; });
    chosen.resize(std::min(chosen.size(), size_t(options.sections)));
    MatchOptions mo;
    mo.tiltMaxIntervalUm = 0;
    mo.shortlist = 3;
    auto scoreAt = [&](double tc, double tr) -> core::Result<double> {
        double total = 0;
        for (size_t k : chosen) {
            std::vector<SliceFeatures> three;
            for (int d = -1; d <= 1; ++d) {
                auto f = planes(matches[k].positionUm + d * options.positionStepUm, tc, tr);
                if (!f && f.error().code == core::ErrorCode::OutOfRange)
                    continue; // beyond the volume's end: that plane is not a candidate
                if (!f)
                    return f.error();
                three.push_back(std::move(*f));
            }
            if (three.empty())
                continue;
            auto m = matchSection(sections[k], three, mo);
            if (m)
                total += m->score;
        }
        return total;
    };
    // The highest-scoring tilt scored so far: the grid's answer (the cross answers with its
    // last vertex instead).
    TiltEstimate bestScored;
    bestScored.score = -1;
    // Scores by tilt, so a tilt the search comes back to is not cut and matched again.
    std::map<std::pair<long, long>, double> scored;
    auto scoreOf = [&](double tc, double tr) -> core::Result<double> {
        const std::pair<long, long> key{std::lround(tc * 1000), std::lround(tr * 1000)};
        if (auto it = scored.find(key); it != scored.end())
            return it->second;
        auto sc = scoreAt(tc, tr);
        if (!sc)
            return sc.error();
        scored.emplace(key, *sc);
        if (*sc > bestScored.score) {
            bestScored.score = *sc;
            bestScored.tiltColumnsDeg = tc;
            bestScored.tiltRowsDeg = tr;
        }
        return *sc;
    };
    TiltEstimate out;
    if (options.method == TiltSearchMethod::Grid) {
        auto grid = [&](double c0, double r0, double half, double step) -> core::Result<void> {
            const int n = int(std::lround(half / step));
            for (int i = -n; i <= n; ++i)
                for (int j = -n; j <= n; ++j)
                    if (auto sc = scoreOf(c0 + i * step, r0 + j * step); !sc)
                        return sc.error();
            return {};
        };
        if (auto r = grid(0, 0, options.maxDeg, options.coarseStepDeg); !r)
            return r.error();
        if (auto r = grid(bestScored.tiltColumnsDeg, bestScored.tiltRowsDeg, options.coarseStepDeg,
                          options.fineStepDeg);
            !r)
            return r.error();
        out = bestScored;
    } else {
        // Vertex of the parabola through (-h, a), (0, b), (h, c), within one step; the best of
        // the three where the scores do not bend down.
        auto vertex = [](double a, double b, double c, double h) {
            const double den = a - 2 * b + c;
            if (den < 0)
                return std::clamp(0.5 * h * (a - c) / den, -h, h);
            return a > b && a >= c ? -h : (c > b && c > a ? h : 0.0);
        };
        const double lim = options.maxDeg;
        double c0 = 0, r0 = 0;
        for (double h = options.coarseStepDeg;; h /= 2) {
            // Grid-aligned to the last step, so the cache serves returning searches.
            const double q = std::min(h, options.fineStepDeg) / 4;
            c0 = std::clamp(std::round(c0 / q) * q, -lim, lim);
            r0 = std::clamp(std::round(r0 / q) * q, -lim, lim);
            auto mid = scoreOf(c0, r0);
            auto cm = scoreOf(c0 - h, r0), cp = scoreOf(c0 + h, r0);
            auto rm = scoreOf(c0, r0 - h), rp = scoreOf(c0, r0 + h);
            for (auto* sc : {&mid, &cm, &cp, &rm, &rp})
                if (!*sc)
                    return sc->error();
            const double dc = vertex(*cm, *mid, *cp, h), dr = vertex(*rm, *mid, *rp, h);
            c0 = std::clamp(c0 + dc, -lim, lim);
            r0 = std::clamp(r0 + dr, -lim, lim);
            if (h <= options.fineStepDeg * 1.0001)
                break;
        }
        // A quadratic surface through every tilt scored within three last steps of the last
        // centre: its vertex, when it bends down both ways and lies within the last step (the
        // scores are noisy at the finest steps; many points average that out).
        if (options.surfaceFit) {
            const double reach = 3 * options.fineStepDeg;
            std::vector<std::array<double, 3>> pts; // tc, tr, score
            for (const auto& [key, sc] : scored) {
                const double tc = double(key.first) / 1000, tr = double(key.second) / 1000;
                if (std::abs(tc - c0) <= reach && std::abs(tr - r0) <= reach)
                    pts.push_back({tc - c0, tr - r0, sc});
            }
            if (pts.size() >= 8) {
                cv::Mat a(int(pts.size()), 6, CV_64F), b(int(pts.size()), 1, CV_64F), x;
                for (int i = 0; i < a.rows; ++i) {
                    const auto& [u, v, f] = pts[size_t(i)];
                    double* r = a.ptr<double>(i);
                    r[0] = 1, r[1] = u, r[2] = v, r[3] = u * u, r[4] = u * v, r[5] = v * v;
                    b.at<double>(i) = f;
                }
                if (cv::solve(a, b, x, cv::DECOMP_SVD)) {
                    const double gx = x.at<double>(1), gy = x.at<double>(2);
                    const double hxx = 2 * x.at<double>(3), hxy = x.at<double>(4),
                                 hyy = 2 * x.at<double>(5);
                    const double det = hxx * hyy - hxy * hxy;
                    if (hxx < 0 && det > 0) {
                        const double du = -(hyy * gx - hxy * gy) / det;
                        const double dv = -(hxx * gy - hxy * gx) / det;
                        if (std::abs(du) <= options.fineStepDeg &&
                            std::abs(dv) <= options.fineStepDeg) {
                            c0 = std::clamp(c0 + du, -lim, lim);
                            r0 = std::clamp(r0 + dv, -lim, lim);
                        }
                    }
                }
            }
        }
        // The answer is the last vertex, not a scored grid point: score it for the record.
        auto fin = scoreOf(std::round(c0 * 1000) / 1000, std::round(r0 * 1000) / 1000);
        if (!fin)
            return fin.error();
        out.tiltColumnsDeg = std::round(c0 * 1000) / 1000;
        out.tiltRowsDeg = std::round(r0 * 1000) / 1000;
        out.score = *fin;
    }
    out.tiltsScored = int(scored.size());
    out.sections = int(chosen.size());
    return out;
}

} // namespace slicestation::pipeline
