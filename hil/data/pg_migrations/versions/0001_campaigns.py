"""The campaign store's tables, each row tagged with its campaign: what a campaign file holds, for many campaigns.

Revision ID: 0001
Revises: none
"""

from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

# Written out here, not imported from hil.data.store: a migration is frozen when it is released.
_REAL_COLUMNS = (
    [f"q{i}_target_rad" for i in range(1, 7)]
    + [f"q{i}_rad" for i in range(1, 7)]
    + [f"T_base_flange_{r}{c}" for r in range(4) for c in range(4)]
    + [f"{kind}{a}_m" for kind in ("", "spread_", "std_") for a in "xyz"]
)
_TABLES = ("campaigns", "campaign_meta", "snapshots", "measurements", "events", "steps", "log", "outcomes")


def upgrade() -> None:
    op.execute(
        """
CREATE TABLE campaigns (
    uuid UUID PRIMARY KEY, label TEXT NOT NULL UNIQUE, created_s DOUBLE PRECISION NOT NULL
);
CREATE TABLE campaign_meta (
    campaign UUID NOT NULL REFERENCES campaigns, key TEXT NOT NULL, value TEXT NOT NULL,
    PRIMARY KEY (campaign, key)
);
CREATE TABLE snapshots (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns,
    recorded_s DOUBLE PRECISION NOT NULL, data TEXT NOT NULL
);
CREATE INDEX snapshots_campaign ON snapshots (campaign, id);
"""
        + f"""
CREATE TABLE measurements (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns,
    procedure TEXT NOT NULL, step TEXT NOT NULL, point_id TEXT NOT NULL,
    {", ".join(f'"{c}" DOUBLE PRECISION' for c in _REAL_COLUMNS)},
    shots INTEGER NOT NULL, rejected_shots TEXT NOT NULL, smr INTEGER NOT NULL, location TEXT NOT NULL,
    temperature_c DOUBLE PRECISION, pressure_hpa DOUBLE PRECISION, humidity_pct DOUBLE PRECISION,
    timestamp_s DOUBLE PRECISION NOT NULL, extra TEXT NOT NULL, recorded_s DOUBLE PRECISION NOT NULL,
    UNIQUE (campaign, procedure, step, point_id)
);
"""
        + """
CREATE INDEX measurements_campaign ON measurements (campaign, id);
CREATE TABLE events (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns, recorded_s DOUBLE PRECISION NOT NULL,
    kind TEXT NOT NULL, message TEXT NOT NULL, procedure TEXT, step TEXT, point_id TEXT, data TEXT NOT NULL
);
CREATE INDEX events_campaign ON events (campaign, id);
CREATE TABLE steps (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns, recorded_s DOUBLE PRECISION NOT NULL,
    procedure TEXT NOT NULL, step TEXT NOT NULL, result TEXT NOT NULL
);
CREATE INDEX steps_campaign ON steps (campaign, procedure, step, id);
CREATE TABLE log (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns, recorded_s DOUBLE PRECISION NOT NULL,
    level TEXT NOT NULL, logger TEXT NOT NULL, message TEXT NOT NULL
);
CREATE INDEX log_campaign ON log (campaign, id);
CREATE TABLE outcomes (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns, recorded_s DOUBLE PRECISION NOT NULL,
    procedure TEXT NOT NULL, measurement TEXT NOT NULL, value DOUBLE PRECISION, unit TEXT NOT NULL,
    limit_value DOUBLE PRECISION, bound TEXT NOT NULL,
    outcome TEXT NOT NULL CHECK (outcome IN ('pass', 'fail', 'not judged')), note TEXT NOT NULL
);
CREATE INDEX outcomes_campaign ON outcomes (campaign, id);
CREATE FUNCTION hil_append_only() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    RAISE EXCEPTION 'hil campaign store is append-only: % rows are never changed or deleted', TG_TABLE_NAME;
END $$;
"""
    )
    for table in _TABLES:
        op.execute(
            f"CREATE TRIGGER {table}_append_only BEFORE UPDATE OR DELETE ON {table} "
            "FOR EACH ROW EXECUTE FUNCTION hil_append_only()"
        )


def downgrade() -> None:
    raise NotImplementedError("a campaign store is never migrated down: recorded data would be dropped")
