"""``proceduralize submit MANIFEST --address URL``: submit a job to a Ray cluster (Ray Jobs API)."""
from __future__ import annotations

import shlex
import time
from pathlib import Path

from service.commands.common import common_parser
from service.commands.jobs import load_manifest_or_report


def register(sub) -> None:
    p = sub.add_parser("submit", parents=[common_parser()], help="submit a job to a Ray cluster (Ray Jobs API)",
                       description="Validate MANIFEST locally, then submit `proceduralize run MANIFEST` to the "
                                   "Ray cluster whose dashboard is at --address (Ray Jobs API). Input maps and "
                                   "the output folder must be on storage the cluster sees (see deploy/README.md).")
    p.add_argument("manifest", type=Path, metavar="MANIFEST")
    p.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://head:8265")
    p.add_argument("--remote-manifest", default=None, metavar="PATH",
                   help="the manifest's path on the cluster (default: the same absolute path)")
    p.add_argument("--working-dir", default=None, metavar="DIR",
                   help="upload this folder as the job's working dir (then MANIFEST is taken relative to it)")
    p.add_argument("--wait", action="store_true", help="follow the job's logs and return its exit status")
    p.set_defaults(handler=handle)


def handle(args) -> int:
    import asyncio

    from ray.job_submission import JobStatus, JobSubmissionClient

    man = load_manifest_or_report(args.manifest)
    if man is None:
        return 2
    if args.remote_manifest:
        remote = args.remote_manifest
    elif args.working_dir:
        remote = str(Path(args.manifest).resolve().relative_to(Path(args.working_dir).resolve()))
    else:
        remote = str(Path(args.manifest).resolve())
    client = JobSubmissionClient(args.address)
    runtime_env = {"working_dir": args.working_dir} if args.working_dir else None
    sid = client.submit_job(entrypoint=f"proceduralize run {shlex.quote(remote)} --address auto",
                            runtime_env=runtime_env,
                            submission_id=f"{man.name}-{int(time.time())}")
    print(f"submitted job {man.name} as {sid} to {args.address}")
    if not args.wait:
        return 0

    async def _tail() -> None:
        async for lines in client.tail_job_logs(sid):
            print(lines, end="")

    asyncio.run(_tail())
    status = client.get_job_status(sid)
    print(f"{sid}: {status}")
    return 0 if status == JobStatus.SUCCEEDED else 1
