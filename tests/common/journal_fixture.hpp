#pragma once
// The journal (SQLite) on real files for tests: a fixture with a directory of its own for the
// journal file, and a run whose sections are each captured once, for the tests that journal
// registrations, flags and series context on top of it.
#include "slicestation/daemon/storage/journal.hpp"
#include "test_dir.hpp"

#include <gtest/gtest.h>

#include <cstdint>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

namespace slicestation::testing_journal {

/// A fixture with an empty directory per test (testing_dir::TempDirTest) for `file()`.
class JournalDirTest : public testing_dir::TempDirTest {
protected:
    explicit JournalDirTest(std::string prefix) : TempDirTest(std::move(prefix)) {}
    /// Where the test's journal lives (not created: Journal::open or sqlite3_open makes it).
    std::filesystem::path file() const { return dir_ / "journal.sqlite"; }
};

/// A run created by runWithCaptures.
struct CapturedRun {
    std::int64_t runId = 0;
    std::vector<std::int64_t> sectionIds; ///< in the plan's order
};

/// Journals a run "r" of `n` sections s1..sn on "slide-1", each captured once (x.tif at 8 um per
/// px). A step that fails is a test failure (EXPECT), and the ids made so far are returned.
inline CapturedRun runWithCaptures(daemon::Journal& j, int n) {
    std::vector<daemon::PlannedSection> planned;
    for (int i = 0; i < n; ++i) {
        daemon::PlannedSection p;
        p.slideName = "slide-1";
        p.index = i;
        p.name = "s" + std::to_string(i + 1);
        planned.push_back(p);
    }
    CapturedRun out;
    auto run = j.createRun("r", {}, {}, planned);
    EXPECT_TRUE(run) << run.error().message;
    if (!run)
        return out;
    out.runId = *run;
    auto sections = j.sections(*run);
    EXPECT_TRUE(sections) << sections.error().message;
    if (!sections)
        return out;
    for (const auto& s : *sections) {
        daemon::CaptureRecord c;
        c.sectionId = s.id;
        c.imagePath = "x.tif";
        c.umPerPx = 8;
        EXPECT_TRUE(j.recordCapture(c));
        out.sectionIds.push_back(s.id);
    }
    return out;
}

} // namespace slicestation::testing_journal
