"""The journal's schema: numbered migrations shared by the SQLite journal and the PostgreSQL
fleet store (one list, translated per engine), and the fleet mode's change-capture triggers."""

from __future__ import annotations

import re

# Each migration is applied once, in order, inside one transaction, and recorded in
# schema_version. Never edit a released step: add a new one. Written in the SQLite dialect;
# ``for_postgres`` maps the few type names that differ, so both engines get the same tables.
MIGRATIONS: list[list[str]] = [
    [  # 1: initial schema
        """CREATE TABLE runs (
            id TEXT PRIMARY KEY, machine TEXT NOT NULL, trigger TEXT NOT NULL,
            state TEXT NOT NULL, reason TEXT NOT NULL DEFAULT '',
            plan TEXT NOT NULL DEFAULT '', artefact TEXT NOT NULL DEFAULT '',
            dialect TEXT NOT NULL DEFAULT '', touch_total INTEGER NOT NULL DEFAULT 0,
            started_at REAL NOT NULL, ended_at REAL,
            verdict TEXT, summary TEXT NOT NULL DEFAULT '', imported INTEGER NOT NULL DEFAULT 0)""",
        "CREATE INDEX runs_machine ON runs(machine, started_at)",
        """CREATE TABLE hits (
            run_id TEXT NOT NULL REFERENCES runs(id), seq INTEGER NOT NULL,
            t_s REAL NOT NULL, repeat INTEGER NOT NULL, pose INTEGER NOT NULL,
            b_cmd_deg REAL NOT NULL, c_cmd_deg REAL NOT NULL, ball TEXT NOT NULL,
            touch INTEGER NOT NULL, dir_x REAL NOT NULL, dir_y REAL NOT NULL, dir_z REAL NOT NULL,
            axes TEXT NOT NULL, triggered INTEGER NOT NULL, feed_mm_min REAL NOT NULL,
            raw TEXT NOT NULL, extra TEXT NOT NULL, received_at REAL NOT NULL,
            PRIMARY KEY (run_id, seq))""",
        """CREATE TABLE centres (
            run_id TEXT NOT NULL REFERENCES runs(id), pose INTEGER NOT NULL, ball TEXT NOT NULL,
            b_deg REAL NOT NULL, c_deg REAL NOT NULL, x_mm REAL NOT NULL, y_mm REAL NOT NULL,
            z_mm REAL NOT NULL, radius_dev_um REAL, form_um REAL,
            PRIMARY KEY (run_id, pose, ball))""",
        """CREATE TABLE estimates (
            run_id TEXT PRIMARY KEY REFERENCES runs(id), analysis TEXT NOT NULL)""",
        """CREATE TABLE verdicts (
            run_id TEXT PRIMARY KEY REFERENCES runs(id), status TEXT NOT NULL,
            reasons TEXT NOT NULL, checks TEXT NOT NULL,
            written_back INTEGER NOT NULL DEFAULT 0)""",
        """CREATE TABLE reports (
            run_id TEXT PRIMARY KEY REFERENCES runs(id), html_path TEXT NOT NULL,
            json_path TEXT NOT NULL)""",
    ],
    [  # 2: HMI sessions signed out before their expiry (cookies are signed, not stored)
        """CREATE TABLE hmi_revoked (
            session_id TEXT PRIMARY KEY, expires_at REAL NOT NULL)""",
    ],
    [  # 3: fleet: each machine's declaration (site, dialect, transport, numeric limits for
        # the fleet trend) and the outbox of rows not yet copied to the fleet store
        """CREATE TABLE machines (
            name TEXT PRIMARY KEY, site TEXT NOT NULL DEFAULT '', dialect TEXT NOT NULL,
            transport TEXT NOT NULL, limits TEXT NOT NULL, updated_at REAL NOT NULL)""",
        """CREATE TABLE outbox (
            seq INTEGER PRIMARY KEY AUTOINCREMENT, kind TEXT NOT NULL, key TEXT NOT NULL,
            hit_seq INTEGER)""",
        "CREATE INDEX outbox_key ON outbox(key, seq)",
    ],
    [  # 4: compensation write-back (daemon/compensation/journal.py): every change to the
        # controller's kinematic model with its old and new values and who confirmed it
        """CREATE TABLE compensations (
            id INTEGER PRIMARY KEY AUTOINCREMENT, machine TEXT NOT NULL,
            run_id TEXT NOT NULL DEFAULT '', family TEXT NOT NULL, state TEXT NOT NULL,
            values_json TEXT NOT NULL, confirmed_by TEXT NOT NULL DEFAULT '',
            reason TEXT NOT NULL DEFAULT '', created_at REAL NOT NULL, applied_at REAL,
            verify_run_id TEXT)""",
        "CREATE INDEX compensations_machine ON compensations(machine, id)",
    ],
    [  # 5: a compensation is one decision: the journal itself refuses a second
        # applied row of a run (and one still being written, 'applying'), and numbers each
        # decision to write a run's values (1, then 2 after a rollback and an explicit --again)
        # so two concurrent writers of the same decision cannot both commit
        "ALTER TABLE compensations ADD COLUMN decision INTEGER",
        """CREATE UNIQUE INDEX compensations_one_applied ON compensations(run_id)
            WHERE state IN ('applied', 'applying')""",
        """CREATE UNIQUE INDEX compensations_decision ON compensations(run_id, decision)
            WHERE decision IS NOT NULL""",
    ],
    [  # 6: the run's compensation view (daemon/compensation/identified.py): its estimate,
        # every parameter with the whole covariance, and the plan of controller changes, as
        # JSON, computed once when the run ends (the view never identifies on the
        # event loop); model_key says which controller model, artefact, held-out poses,
        # controller values and coverage factor they were computed for
        """CREATE TABLE link_estimates (
            run_id TEXT PRIMARY KEY REFERENCES runs(id), model_key TEXT NOT NULL,
            estimate TEXT NOT NULL, plan TEXT NOT NULL, created_at REAL NOT NULL)""",
    ],
    [  # 7: people, not a shared token: the person who started a run (an
        # HMI account; '' for the controller, the CAN panel or a script) and every start,
        # abort, compensation confirm and rollback a person asked for on the HMI, with the
        # person's name and role (daemon/store/actions.py)
        "ALTER TABLE runs ADD COLUMN started_by TEXT NOT NULL DEFAULT ''",
        """CREATE TABLE hmi_actions (
            id INTEGER PRIMARY KEY AUTOINCREMENT, at REAL NOT NULL, machine TEXT NOT NULL,
            run_id TEXT NOT NULL DEFAULT '', action TEXT NOT NULL, person TEXT NOT NULL,
            role TEXT NOT NULL, via TEXT NOT NULL, outcome TEXT NOT NULL,
            detail TEXT NOT NULL DEFAULT '')""",
        "CREATE INDEX hmi_actions_machine ON hmi_actions(machine, id)",
    ],
    [  # 8: temperature channels: every reading of a run (start, each pose,
        # end) committed on arrival like a hit; value_c NULL with the error when unreadable
        """CREATE TABLE temperatures (
            run_id TEXT NOT NULL REFERENCES runs(id), seq INTEGER NOT NULL,
            channel TEXT NOT NULL, at TEXT NOT NULL, pose INTEGER, t_s REAL NOT NULL,
            value_c REAL, error TEXT NOT NULL DEFAULT '', received_at REAL NOT NULL,
            PRIMARY KEY (run_id, seq))""",
    ],
    [  # 9: each machine's drift baseline (daemon/store/baselines.py): a run
        # a person confirmed (or the daemon proposed after a compensation), who and when
        """CREATE TABLE baselines (
            id INTEGER PRIMARY KEY AUTOINCREMENT, machine TEXT NOT NULL,
            run_id TEXT NOT NULL REFERENCES runs(id), state TEXT NOT NULL,
            by_person TEXT NOT NULL, at REAL NOT NULL, note TEXT NOT NULL DEFAULT '')""",
        "CREATE INDEX baselines_machine ON baselines(machine, id)",
    ],
    [  # 10: a run's report job (daemon/store/report_jobs.py), no longer in the run's reason:
        # writing → written | failed with its reason, started and ended. A journal of before
        # keeps its reports (written) and its "report not written" reasons (failed, with the
        # cause after the old prefix, 42 characters; the run's reason kept as it was); a DONE
        # run with neither had no job to tell of (no row).
        """CREATE TABLE report_jobs (
            run_id TEXT PRIMARY KEY REFERENCES runs(id), state TEXT NOT NULL,
            reason TEXT NOT NULL DEFAULT '', started_at REAL NOT NULL, ended_at REAL)""",
        """INSERT INTO report_jobs (run_id, state, reason, started_at, ended_at)
            SELECT p.run_id, 'written', '', COALESCE(r.ended_at, r.started_at), r.ended_at
            FROM reports p JOIN runs r ON r.id = p.run_id""",
        """INSERT INTO report_jobs (run_id, state, reason, started_at, ended_at)
            SELECT id, 'failed',
            CASE WHEN reason LIKE 'verdict written back; report not written: %'
            THEN substr(reason, 43) ELSE reason END, COALESCE(ended_at, started_at), ended_at
            FROM runs
            WHERE state = 'DONE' AND reason LIKE '%report not written%'
            AND id NOT IN (SELECT run_id FROM reports)""",
    ],
    [  # 11: the program a temperature reading came from: 0 the plan's, k the k-th
        # re-probe round's, which prints its own start, pose and end lines over DNC; readings
        # journaled before are the plan's (a re-probe's were not told apart)
        "ALTER TABLE temperatures ADD COLUMN reprobe_round INTEGER NOT NULL DEFAULT 0",
    ],
    [  # 12: maps of the linear axes (daemon/store/map_results.py): a map's figures, verdict
        # and the path and SHA-256 of its map file and report; id = the daemon job's run id,
        # or a map-… id for a map made by `rumba map --store`. fleet_copied: 0 not yet copied
        # to the fleet store, 1 copied, 2 refused there (the id taken by another machine)
        """CREATE TABLE map_results (
            id TEXT PRIMARY KEY, machine TEXT NOT NULL, run_id TEXT NOT NULL DEFAULT '',
            created_at REAL NOT NULL, verdict TEXT, volumetric_max_um REAL NOT NULL,
            volumetric_max_u_um REAL, volumetric_rms_um REAL NOT NULL,
            limit_text TEXT NOT NULL DEFAULT '', placements INTEGER NOT NULL,
            figures TEXT NOT NULL, json_path TEXT NOT NULL, json_sha256 TEXT NOT NULL,
            report_html TEXT NOT NULL DEFAULT '', report_sha256 TEXT NOT NULL DEFAULT '',
            recorded_by TEXT NOT NULL DEFAULT '', fleet_copied INTEGER NOT NULL DEFAULT 0)""",
        "CREATE INDEX map_results_machine ON map_results(machine, created_at)",
    ],
]
SCHEMA_VERSION = len(MIGRATIONS)

_PG_TYPES = [(re.compile(r"\bREAL\b"), "DOUBLE PRECISION"),
             (re.compile(r"\bINTEGER PRIMARY KEY AUTOINCREMENT\b"),
              "BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY"),
             (re.compile(r"\bINTEGER\b"), "BIGINT")]


def for_postgres(stmt: str) -> str:
    """A migration statement in PostgreSQL's dialect: REAL is 4 bytes there (SQLite's is 8),
    AUTOINCREMENT is an identity column; everything else is standard SQL both accept."""
    for pattern, repl in _PG_TYPES:
        stmt = pattern.sub(repl, stmt)
    return stmt


# Change capture of the fleet mode (daemon/store/drain.py): every write to a replicated table
# adds an outbox row in the same transaction, so a row committed locally is either in the
# outbox or already copied, never forgotten (a kill between the two cannot happen). TEMP
# triggers live on the daemon's own connection only: a journal opened without a fleet URL
# records nothing, and ``rumba_outbox_wake()`` (a Python function of that connection) wakes the
# drainer at once instead of it polling.
CAPTURE_TRIGGERS: list[str] = [
    *(f"""CREATE TEMP TRIGGER IF NOT EXISTS outbox_{t}_{op.lower()} AFTER {op} ON main.{t}
          BEGIN INSERT INTO outbox(kind, key) VALUES ('{t}', NEW.{k});
          SELECT rumba_outbox_wake(); END"""
      for t, k in (("runs", "id"), ("centres", "run_id"), ("estimates", "run_id"),
                   ("link_estimates", "run_id"), ("verdicts", "run_id"),
                   ("reports", "run_id"), ("machines", "name"),
                   ("baselines", "run_id"),  # a person's baseline decisions
                   ("report_jobs", "run_id"))
      for op in ("INSERT", "UPDATE")),
    """CREATE TEMP TRIGGER IF NOT EXISTS outbox_hits_insert AFTER INSERT ON main.hits
       BEGIN INSERT INTO outbox(kind, key, hit_seq) VALUES ('hits', NEW.run_id, NEW.seq);
       SELECT rumba_outbox_wake(); END""",
    # temperature readings, journaled on arrival like hits and copied like them
    """CREATE TEMP TRIGGER IF NOT EXISTS outbox_temperatures_insert AFTER INSERT ON
       main.temperatures BEGIN INSERT INTO outbox(kind, key, hit_seq)
       VALUES ('temperatures', NEW.run_id, NEW.seq); SELECT rumba_outbox_wake(); END""",
]
# Readings journaled before their trigger existed (a daemon upgraded while runs waited in the
# outbox for the fleet store): queued with their run when the drainer starts, once each — no
# schema step, the table is in both engines since migration 8 and only the fleet mode's
# connection has an outbox to fill. Runs already copied keep their summary in the analysis.
QUEUE_TEMPERATURES = """INSERT INTO outbox(kind, key, hit_seq)
    SELECT 'temperatures', t.run_id, t.seq FROM temperatures t
    WHERE t.run_id IN (SELECT key FROM outbox WHERE kind != 'machines')
    AND NOT EXISTS (SELECT 1 FROM outbox o WHERE o.kind = 'temperatures'
                    AND o.key = t.run_id AND o.hit_seq = t.seq)"""
