#pragma once
// The journal's schema versions exactly as shipped (daemon/storage/journal.cpp): files
// written by earlier releases, for the migration tests. Never edit a shipped one; append the next.

namespace slicestation::testing_journal {

// Version 1 of the schema exactly as shipped (daemon/storage/journal.cpp, kMigration1): a file
// written by the previous release, to migrate.
constexpr const char* kShippedVersion1 = R"sql(
CREATE TABLE runs (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('queued','running','paused','finished','failed','cancelled')),
    reason TEXT NOT NULL DEFAULT '',
    plan_json TEXT NOT NULL,
    settings_json TEXT NOT NULL,
    created_utc TEXT NOT NULL,
    started_utc TEXT NOT NULL DEFAULT '',
    ended_utc TEXT NOT NULL DEFAULT ''
);
CREATE TABLE sections (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    slide_index INTEGER NOT NULL,
    slide_name TEXT NOT NULL,
    idx INTEGER NOT NULL,
    name TEXT NOT NULL,
    x_um REAL NOT NULL, y_um REAL NOT NULL,
    width_um REAL NOT NULL, height_um REAL NOT NULL,
    expected_slice INTEGER,
    state TEXT NOT NULL CHECK (state IN ('pending','captured','registered','damaged','rescan','failed')),
    reason TEXT NOT NULL DEFAULT '',
    UNIQUE (run_id, slide_index, idx)
);
CREATE TABLE captures (
    id INTEGER PRIMARY KEY,
    section_id INTEGER NOT NULL REFERENCES sections(id) ON DELETE CASCADE,
    attempt INTEGER NOT NULL,
    image_path TEXT NOT NULL,
    um_per_px REAL NOT NULL CHECK (um_per_px > 0),
    stage_x_um REAL NOT NULL, stage_y_um REAL NOT NULL, stage_z_um REAL NOT NULL,
    focus_score REAL,
    focus_found INTEGER NOT NULL,
    tiles INTEGER NOT NULL,
    exposure_us INTEGER NOT NULL,
    gain REAL NOT NULL,
    captured_utc TEXT NOT NULL,
    UNIQUE (section_id, attempt)
);
CREATE TABLE registrations (
    id INTEGER PRIMARY KEY,
    capture_id INTEGER NOT NULL UNIQUE REFERENCES captures(id) ON DELETE CASCADE,
    atlas_slice INTEGER NOT NULL,
    matched_slice INTEGER,
    damaged INTEGER NOT NULL,
    damage_fraction REAL NOT NULL,
    summary TEXT NOT NULL,
    warning TEXT NOT NULL,
    quality REAL NOT NULL,
    result_path TEXT NOT NULL,
    overlay_path TEXT NOT NULL,
    labels_path TEXT NOT NULL,
    result_json TEXT NOT NULL,
    registered_utc TEXT NOT NULL
);
CREATE TABLE alerts (
    id INTEGER PRIMARY KEY,
    run_id INTEGER REFERENCES runs(id) ON DELETE SET NULL,
    section_id INTEGER REFERENCES sections(id) ON DELETE SET NULL,
    kind TEXT NOT NULL,
    severity TEXT NOT NULL CHECK (severity IN ('info','warning','critical')),
    message TEXT NOT NULL,
    raised_utc TEXT NOT NULL,
    acknowledged_utc TEXT,
    ack_action TEXT NOT NULL DEFAULT ''
);
CREATE INDEX sections_by_run ON sections(run_id, slide_index, idx);
CREATE INDEX captures_by_section ON captures(section_id, attempt);
CREATE INDEX alerts_open ON alerts(acknowledged_utc);
)sql";

// Version 2 as shipped (kMigration2), applied on top of version 1.
constexpr const char* kShippedVersion2 = R"sql(
ALTER TABLE registrations ADD COLUMN damage_score REAL
    CHECK (damage_score IS NULL OR (damage_score >= 0 AND damage_score <= 1));
ALTER TABLE registrations ADD COLUMN damage_verdict TEXT
    CHECK (damage_verdict IS NULL OR damage_verdict IN ('clean','damaged','check_registration'));
ALTER TABLE registrations ADD COLUMN flag_score REAL
    CHECK (flag_score IS NULL OR (flag_score >= 0 AND flag_score <= 1));
CREATE TABLE station_settings (
    key TEXT PRIMARY KEY,
    value_json TEXT NOT NULL,
    set_utc TEXT NOT NULL
);
CREATE INDEX alerts_by_kind ON alerts(kind, raised_utc);
)sql";

} // namespace slicestation::testing_journal
