-- Windows of a long log fitted by workers other than the job's own (src/jobs/worker.rs,
-- Worker::try_help): one claim per window under a lease, so that no window is fitted twice at
-- once and a helper that dies loses its claim. Claims end with their job.
CREATE TABLE window_claims (
    job_id uuid NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    key text NOT NULL,
    worker text NOT NULL,
    lease_expires_at bigint NOT NULL,
    PRIMARY KEY (job_id, key)
);
