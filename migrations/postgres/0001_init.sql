-- The fleet's store (src/store/postgres.rs): sequences, uploads in progress and the job queue.
-- Frames and models live in the object store; these rows say which objects are committed.
--
-- Times are bigint milliseconds since the Unix epoch (what the records carry). Every time the
-- queue compares (leases) comes from mbnt_now_ms(), the database's clock, so that workers on
-- machines whose clocks disagree still agree on when a lease ends.
CREATE FUNCTION mbnt_now_ms() RETURNS bigint LANGUAGE sql VOLATILE
    AS $$ SELECT floor(extract(epoch FROM clock_timestamp()) * 1000)::bigint $$;

CREATE TABLE sequences (
    id uuid PRIMARY KEY,
    -- insertion order, to break ties between equal creation times
    ord bigint GENERATED ALWAYS AS IDENTITY,
    name text,
    -- JSON as text, not jsonb: jsonb rewrites numbers, text keeps serde_json's exact f64s
    points_per_frame text NOT NULL,
    timestamps text,
    poses text,
    created_at bigint NOT NULL
);
CREATE INDEX sequences_newest ON sequences (created_at DESC, ord DESC);

-- A sequence being uploaded: its frame objects exist, its row does not yet. The janitor
-- (PgStore::sweep_orphans) removes the objects of uploads untouched for long, and objects that
-- neither a sequence nor an upload claims.
CREATE TABLE uploads (
    id uuid PRIMARY KEY,
    touched_at bigint NOT NULL
);

CREATE TABLE jobs (
    id uuid PRIMARY KEY,
    ord bigint GENERATED ALWAYS AS IDENTITY,
    -- the key share lock an insert takes here waits for a delete of the sequence in progress
    sequence_id uuid NOT NULL REFERENCES sequences (id),
    method text NOT NULL,
    params text NOT NULL,
    status text NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    progress text NOT NULL,
    error text,
    cancel_requested boolean NOT NULL DEFAULT false,
    attempts integer NOT NULL DEFAULT 0 CHECK (attempts >= 0),
    created_at bigint NOT NULL,
    started_at bigint,
    finished_at bigint,
    worker text,
    lease_expires_at bigint
);
-- the claim scans active jobs oldest first
CREATE INDEX jobs_active_oldest ON jobs (created_at, ord) WHERE status IN ('queued', 'running');
CREATE INDEX jobs_newest ON jobs (created_at DESC, ord DESC);
CREATE INDEX jobs_by_sequence ON jobs (sequence_id);
CREATE INDEX jobs_by_status ON jobs (status);
