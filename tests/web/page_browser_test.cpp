// The station's web page in a real browser (headless Chromium through chromedriver) against a
// station scanning a simulated slide in this process: sections appear in the run grid as they
// are captured, the torn one turns red with its overlay, hovering names atlas regions, the alert
// is acknowledged from the banner (with the control token), and the page fits a phone screen.
// Screenshots are saved under the build directory as test artefacts (docs/web.md shows them).
#include "../daemon/station_fixture.hpp"
#include "webdriver.hpp"

#include <httplib.h>

#include <functional>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;
using namespace std::chrono_literals;

namespace {

const std::filesystem::path kArtefacts =
    std::filesystem::path(SLST_BINARY_DIR) / "test-artefacts" / "web";

class PageTest : public StationTest {
protected:
    /// Polls `ready` (the page updates asynchronously) for up to `limit`. Generous: in the
    /// sanitizer build the run's third section is registered 44-50 s after the start on an idle
    /// 2-core machine, and one CI run on a loaded machine missed a 60 s limit.
    static bool waitFor(const std::function<bool()>& ready, std::chrono::seconds limit = 180s) {
        const auto deadline = std::chrono::steady_clock::now() + limit;
        while (std::chrono::steady_clock::now() < deadline) {
            if (ready())
                return true;
            std::this_thread::sleep_for(100ms);
        }
        return ready();
    }
    /// data-state of the grid cell of a section (cells are redrawn: looked up each time).
    static nlohmann::json cellState(webdriver::Session& b, std::int64_t sectionId) {
        return b.execute("const e = document.querySelector('#grid .cell[data-section-id=\"' + "
                         "arguments[0] + '\"]'); "
                         "return e ? e.dataset.state : null;",
                         {std::to_string(sectionId)});
    }
    static std::string expectedCell(const SectionRecord& s) {
        const std::string st = toString(s.state);
        if (s.state == SectionState::Registered && s.attempts > 1)
            return "rescanned";
        return st;
    }
};

} // namespace

TEST_F(PageTest, TechnicianWatchesARunSeesTheTornSectionAndAcknowledgesItsAlert) {
    build();
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    const std::string base = "http://127.0.0.1:" + std::to_string(rig_.api->port());
    rig_.station->start();

    webdriver::Session browser(1280, 1100);
    browser.navigate(base + "/");
    ASSERT_TRUE(waitFor([&] { return browser.text(*browser.find("#state")) == "idle"; }))
        << "the page shows the station's state";
    EXPECT_EQ(browser.text(*browser.find("#grid")), "no run yet");

    // A run starts: its sections appear in the grid, then the torn one (the third) turns red.
    auto runId = rig_.station->submitPlan(planFor({0, 1, 2, 3}), "browser-run");
    ASSERT_TRUE(runId) << runId.error().message;
    ASSERT_TRUE(waitFor([&] { return browser.findAll("#grid .cell").size() == 4; }))
        << "the run's four sections appear in the grid";
    auto secs = rig_.station->journal().sections(*runId);
    ASSERT_TRUE(secs);
    const std::int64_t torn = (*secs)[2].id;
    const std::string tornCell = "#grid .cell[data-section-id=\"" + std::to_string(torn) + "\"]";
    ASSERT_TRUE(waitFor([&] { return cellState(browser, torn) == "damaged"; }))
        << "the torn section turns damaged in the grid";
    const auto colour = browser.execute(
        "return getComputedStyle(document.querySelector(arguments[0])).backgroundColor;",
        {tornCell});
    EXPECT_EQ(colour, "rgb(212, 60, 60)") << "damaged cells are red";

    // The damage alert has its banner (one per open alert), naming the damage, with both answers.
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("return document.querySelector('#banners .banner') !== null;") ==
               true;
    }));
    auto damageAlerts = alertsOf("damaged");
    ASSERT_EQ(damageAlerts.size(), 1u);
    const std::string damageBanner =
        "#banners .banner[data-alert-id=\"" + std::to_string(damageAlerts[0].id) + "\"]";
    ASSERT_TRUE(waitFor([&] { return browser.find(damageBanner).has_value(); }))
        << "the banner shows the damage alert";
    EXPECT_NE(browser.text(*browser.find(damageBanner + " .banner-text")).find("damaged"),
              std::string::npos);

    // Clicking a section opens its detail and shows its overlay: the torn one has its damage
    // filled in red, a clean one has no red at all.
    waitRun(*runId, RunState::Finished);
    auto showSection = [&](std::int64_t id) {
        browser.clickCss("#grid .cell[data-section-id=\"" + std::to_string(id) + "\"]");
        return waitFor([&] {
            return browser.execute("const i = document.getElementById('overlay'); return "
                                   "i.complete && i.naturalWidth > 0 && "
                                   "i.dataset.sectionId === arguments[0];",
                                   {std::to_string(id)}) == true;
        });
    };
    auto redShare = [&] {
        return browser
            .execute(R"(
            const i = document.getElementById('overlay');
            const c = document.createElement('canvas'); c.width = i.naturalWidth; c.height = i.naturalHeight;
            const g = c.getContext('2d'); g.drawImage(i, 0, 0);
            const d = g.getImageData(0, 0, c.width, c.height).data;
            let n = 0; for (let k = 0; k < d.length; k += 4) if (d[k] > 150 && d[k + 1] < 90 && d[k + 2] < 90) ++n;
            return n / (c.width * c.height);)")
            .get<double>();
    };
    ASSERT_TRUE(showSection((*secs)[0].id)) << "the overlay of a clean section is shown";
    EXPECT_LT(redShare(), 1e-4) << "no red on a clean section";
    ASSERT_TRUE(showSection(torn)) << "the overlay of the torn section is shown";
    EXPECT_GT(redShare(), 4e-4) << "damage is filled in red on the overlay";
    ASSERT_TRUE(waitFor(
        [&] { return browser.find("#regions") && browser.find("#detail table").has_value(); }));
    const std::string detail = browser.text(*browser.find("#detail"));
    EXPECT_NE(detail.find("damaged"), std::string::npos) << detail;
    EXPECT_NE(detail.find("Atlas slice"), std::string::npos) << detail;
    EXPECT_GT(browser.findAll("#regions tr").size(), 4u) << "the region list with names";

    // Hovering the centre of the overlay names the atlas region there, the one the API gives.
    auto overlay = browser.find("#overlay");
    browser.hover(*overlay, 0, 0);
    ASSERT_TRUE(waitFor(
        [&] {
            return browser.execute(
                       "return getComputedStyle(document.getElementById('region-tip')).display;") ==
                   "block";
        },
        10s));
    const std::string tip = browser.text(*browser.find("#region-tip"));
    httplib::Client cli("127.0.0.1", rig_.api->port());
    const auto natural = browser.execute(
        "const i = document.getElementById('overlay'); return [i.naturalWidth, i.naturalHeight];");
    const int nw = natural[0].get<int>(), nh = natural[1].get<int>();
    auto region =
        cli.Get("/api/sections/" + std::to_string(torn) + "/region?x=" + std::to_string(nw / 2) +
                "&y=" + std::to_string(nh / 2) + "&of_width=" + std::to_string(nw));
    ASSERT_TRUE(region);
    const auto rj = nlohmann::json::parse(region->body);
    ASSERT_GT(rj["id"].get<int>(), 0) << "the centre of the section is brain";
    EXPECT_EQ(tip, rj["name"].get<std::string>() + " (" + rj["acronym"].get<std::string>() + ")");
    browser.screenshot(kArtefacts / "page-damaged-section.png");

    // The zoomed view of the torn section: read at full resolution, magnified around the tear.
    browser.clickCss("#zoom-open");
    ASSERT_TRUE(waitFor(
        [&] {
            return browser.execute("const i = document.getElementById('zoom-img'); return "
                                   "i.complete && i.dataset.fitted === 'yes' && i.naturalWidth >= "
                                   "arguments[0];",
                                   {nw}) == true;
        },
        10s))
        << "the zoom reads at least the view's pixels; it has "
        << browser.execute("return document.getElementById('zoom-img').naturalWidth;")
        << " (the view " << nw << ")";
    std::cout << "zoom: "
              << browser.execute("return document.getElementById('zoom-img').naturalWidth;")
              << " px wide, the view " << nw << " px\n";
    browser.clickCss("#zoom-in");
    browser.clickCss("#zoom-in");
    browser.screenshot(kArtefacts / "page-zoom.png");
    browser.clickCss("#zoom-close");

    // The grid agrees with the journal, cell by cell.
    secs = rig_.station->journal().sections(*runId);
    ASSERT_TRUE(secs);
    for (const auto& s : *secs) {
        EXPECT_EQ(cellState(browser, s.id), expectedCell(s)) << s.name;
    }

    // Acknowledge from the banner: without the token the page asks for it, then it goes through.
    ASSERT_TRUE(waitFor([&] { return browser.find(damageBanner).has_value(); }));
    browser.clickCss(damageBanner + " button.ack-rescan");
    ASSERT_TRUE(waitFor(
        [&] {
            return browser.execute(
                       "return "
                       "document.getElementById('token-row').classList.contains('shown');") == true;
        },
        10s))
        << "a 401 asks for the control token";
    auto still = rig_.station->journal().alert(damageAlerts[0].id);
    ASSERT_TRUE(still);
    EXPECT_FALSE(still->acknowledgedUtc) << "nothing acknowledged without the token";
    browser.type(*browser.find("#token"), kToken);
    browser.clickCss("#token-save");
    browser.clickCss(damageBanner + " button.ack-rescan");
    ASSERT_TRUE(waitFor(
        [&] {
            auto a = rig_.station->journal().alert(damageAlerts[0].id);
            return a && a->acknowledgedUtc.has_value();
        },
        10s))
        << "the alert is acknowledged from the page";
    EXPECT_EQ(rig_.station->journal().alert(damageAlerts[0].id)->ackAction, "rescan");
    // The rescan captures the section again (the simulated slide still holds a torn section).
    ASSERT_TRUE(waitFor(
        [&] {
            auto s = rig_.station->journal().section(torn);
            return s && s->attempts == 2 &&
                   (s->state == SectionState::Damaged || s->state == SectionState::Registered);
        },
        120s))
        << "the rescan ran";
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("const li = [...document.querySelectorAll('#alerts li')]; "
                               "return li.some(e => e.textContent.includes('[rescan]'));") == true;
    })) << "the acknowledged alert is listed with its answer";
    browser.screenshot(kArtefacts / "page-after-acknowledge.png");

    // A phone-sized screen: one column, nothing wider than the screen.
    browser.resize(390, 844);
    ASSERT_TRUE(waitFor(
        [&] { return browser.execute("return window.innerWidth;").get<int>() <= 420; }, 10s));
    EXPECT_EQ(browser.execute(
                  "const d = document.documentElement; return d.scrollWidth <= d.clientWidth;"),
              true)
        << "no horizontal scrolling on a phone";
    EXPECT_EQ(
        browser.execute(
            "return getComputedStyle(document.querySelector('main')).gridTemplateColumns.split(' "
            "').length;"),
        1);
    browser.screenshot(kArtefacts / "page-phone.png");
}

TEST_F(PageTest, TheLiveViewShowsCameraFramesDuringARun) {
    build();
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    rig_.station->start();
    webdriver::Session browser(1280, 900);
    browser.navigate("http://127.0.0.1:" + std::to_string(rig_.api->port()) + "/");
    ASSERT_TRUE(waitFor([&] { return browser.text(*browser.find("#state")) == "idle"; }));
    EXPECT_EQ(browser.execute("return document.getElementById('live').naturalWidth;"), 0)
        << "no frame before a run";
    auto runId = rig_.station->submitPlan(planFor({0, 1, 2, 3}), "live-run");
    ASSERT_TRUE(runId);
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("const i = document.getElementById('live'); return "
                               "i.src.startsWith('blob:') && i.naturalWidth === 800;") == true;
    })) << "the live view shows a frame scaled to 800 px";
    waitRun(*runId, RunState::Finished);
}
