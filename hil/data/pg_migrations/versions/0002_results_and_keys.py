"""Results belong to their campaign (the models and summaries of calibrate and diagnose), and every campaign is
keyed by what identifies it in a plant: the view campaign_keys reads the robot, the controller, the tracker,
the cell and the operator from the campaign's latest station snapshot, and its dates and temperatures from its
measurements.

Revision ID: 0002
Revises: 0001
"""

from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.execute(
        """
CREATE TABLE results (
    id BIGSERIAL PRIMARY KEY, campaign UUID NOT NULL REFERENCES campaigns, recorded_s DOUBLE PRECISION NOT NULL,
    kind TEXT NOT NULL, summary TEXT NOT NULL, model TEXT
);
CREATE INDEX results_campaign ON results (campaign, id);
CREATE INDEX results_kind ON results (kind, recorded_s);
CREATE TRIGGER results_append_only BEFORE UPDATE OR DELETE ON results
    FOR EACH ROW EXECUTE FUNCTION hil_append_only();
CREATE VIEW campaign_keys AS
SELECT
    c.uuid, c.label, c.created_s,
    NULLIF(s.data #>> '{station,cell_name}', '') AS cell_name,
    NULLIF(s.data #>> '{station,operator_name}', '') AS operator_name,
    COALESCE(NULLIF(s.data #>> '{station,robot_model_reported}', ''), s.data #>> '{robot_definition,model}')
        AS robot_model,
    NULLIF(s.data #>> '{station,robot_serial_number}', '') AS robot_serial,
    NULLIF(s.data #>> '{station,robot_controller_version}', '') AS controller_version,
    NULLIF(s.data #>> '{station,tracker,name}', '') AS tracker_name,
    NULLIF(s.data #>> '{station,tracker,serial_number}', '') AS tracker_serial,
    NULLIF(s.data #>> '{station,tracker,software_version}', '') AS tracker_software,
    m.points, m.first_s, m.last_s, m.temperature_min_c, m.temperature_max_c
FROM campaigns c
LEFT JOIN LATERAL (
    SELECT data::jsonb AS data FROM snapshots WHERE campaign = c.uuid ORDER BY id DESC LIMIT 1
) s ON true
LEFT JOIN LATERAL (
    SELECT count(*) AS points, min(timestamp_s) AS first_s, max(timestamp_s) AS last_s,
        min(temperature_c) AS temperature_min_c, max(temperature_c) AS temperature_max_c
    FROM measurements WHERE campaign = c.uuid
) m ON true;
"""
    )


def downgrade() -> None:
    raise NotImplementedError("a campaign store is never migrated down: recorded data would be dropped")
