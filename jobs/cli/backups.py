"""`dncq backup run|list|show|download|verify|diff|restore`: stored backups from the CLI."""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.text import Text
from rich.tree import Tree

from jobs.cli.backup_follow import follow_backup
from jobs.cli.common import (
    OutputOpt,
    SinceOpt,
    UntilOpt,
    api_call,
    counted,
    listing,
    local_time,
    out,
    saved_at,
    segment,
    when,
    whole,
)
from jobs.cli.common import download as cli_download
from jobs.cli.help_names import Cli
from jobs.cli.job_follow import started
from jobs.cli.jobs import (
    MAYBE_RESTORING,
    WAIT,
    AllOpt,
    AnywayOpt,
    DirOpt,
    DryOpt,
    TagOpt,
    ToOpt,
    WaitOpt,
    selector,
    submit,
)

backup_app = Cli(help="Stored backups: make, list, verify, compare, restore.",
                         no_args_is_help=True)


@backup_app.command("run")
def run(to: ToOpt = None, tag: TagOpt = None, all_: AllOpt = False, folder: DirOpt = None,
        no_subdirs: Annotated[bool, typer.Option("--no-subdirs",
                                                 help="Only the folder's own files")] = False,
        dry_run: DryOpt = False, anyway: AnywayOpt = False,
        wait: WaitOpt = WAIT) -> None:
    """Back up machines (their whole root, or --dir) into one stored ZIP."""
    request = {"kind": "backup", "machines": selector(to, tag, all_), "dirAtCNC": folder,
               "includeSubDir": not no_subdirs, "dry_run": dry_run, "allow_unknown": anyway,
               "created_by": "cli"}
    submit(request, wait, said="Backup job {id}: {total}.", counting="machine",
           then=follow_backup)


ABSENT = "absent"  # the API's word for a machine a backup does not hold


@backup_app.command("list")
def list_(since: SinceOpt = None, until: UntilOpt = None,
          machine: Annotated[str | None, typer.Option(help="Backups that hold this machine")]
          = None,
          state: Annotated[str | None, typer.Option(help="complete, partial or failed")] = None,
          limit: Annotated[int, typer.Option(min=1, help="At most this many")] = 100) -> None:
    """Stored backups, newest first."""
    params = {k: v for k, v in (("since", when(since)), ("until", when(until)),
                                ("machine", machine), ("state", state), ("limit", limit))
              if v is not None}
    # The archive's name comes last, cut short where the terminal is narrow: the id is what
    # the other commands take, and `backup show` gives the name whole.
    table = listing(*whole("id", "created", "status", "machines", "files", "bytes"), "name")
    for b in api_call("GET", "/api/backups", params=params):
        # The API's word for MachineBackupStatus.OK: jobs.backup_models would load SQLAlchemy.
        ok = sum(m["status"] == "ok" for m in b["machines"])
        table.add_row(b["id"], local_time(b["createdAt"]), b["status"],
                      f"{ok}/{len(b['machines'])}", str(b["files"]), str(b["size"]), b["name"])
    out.print(table)


@backup_app.command()
def show(backup_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """A backup's manifest as a tree: machine, folders, files with size and SHA-256."""
    found = api_call("GET", f"/api/backups/{segment(backup_id)}/manifest")
    created = local_time(found["createdAt"], seconds=True)
    tree = Tree(Text(f"{found['name']} ({found['status']}, {len(found['files'])} files, "
                     f"{found['size']} bytes, {created})", style="bold"))
    files_of: dict[str, list[dict[str, Any]]] = {}
    for f in found["files"]:
        files_of.setdefault(f["machineID"], []).append(f)
    for m in found["machines"]:
        label = f"{m['machineID']} {m['machineName']}: {m['status']}"
        if m["errorCode"]:
            said = m["statusMsg"]
            detail = f" - {said}" if said and said != m["errorMsg"] else ""
            label += f" ({m['errorCode']} {m['errorMsg']}{detail})"
        branch = tree.add(Text(label))
        folders: dict[tuple[str, ...], Tree] = {(): branch}
        for f in sorted(files_of.get(m["machineID"], []), key=lambda f: f["archivePath"]):
            *dirs, name = f["archivePath"].split("/")
            for depth in range(1, len(dirs) + 1):
                key = tuple(dirs[:depth])
                if key not in folders:
                    folders[key] = folders[key[:-1]].add(Text(f"{key[-1]}/"))
            folders[tuple(dirs)].add(Text(f"{name}  {f['size']} bytes  {f['sha256'][:12]}"))
    out.print(tree, soft_wrap=False)  # a long line wraps under its branch, not cut at the edge


@backup_app.command()
def download(backup_id: Annotated[str, typer.Argument(metavar="ID")],
             output: OutputOpt = None) -> None:
    """Download a stored backup's ZIP (streamed; nothing is left of a broken download)."""
    target = saved_at(output, lambda: api_call(
        "GET", f"/api/backups/{segment(backup_id)}/manifest")["name"])
    cli_download(f"/api/backups/{segment(backup_id)}", target, what=f"backup {backup_id}")


@backup_app.command()
def verify(backup_id: Annotated[str, typer.Argument(metavar="ID")]) -> None:
    """Re-read a backup ZIP and check every CRC and SHA-256; exit 1 on any problem."""
    found = api_call("POST", f"/api/backups/{segment(backup_id)}/verify")
    if found["ok"]:
        out.print(f"Backup {backup_id} is sound.")
        return
    for problem in found["problems"]:
        out.print(problem, style="red", highlight=False)
    raise typer.Exit(1)


@backup_app.command()
def diff(first: Annotated[str, typer.Argument(metavar="A")],
         second: Annotated[str, typer.Argument(metavar="B")],
         machine: Annotated[str | None, typer.Option(help="Only this machine")] = None) -> None:
    """Files added, removed and changed per machine from backup A to backup B."""
    params = {"machine": machine} if machine else {}
    path = f"/api/backups/{segment(first)}/diff/{segment(second)}"
    changes: dict[str, Any] = api_call("GET", path, params=params)
    for machine_id, found in changes.items():
        if not any(found.values()):
            continue
        out.print(machine_id, style="bold")
        if set(found["incomplete"].values()) == {ABSENT} and len(found["incomplete"]) == \
                len({first, second}):
            out.print(f"  ! neither backup holds machine {machine_id}", style="yellow",
                      highlight=False)
            continue
        for backup, status in found["incomplete"].items():
            some = "only some" if status == "partial" else "none"
            out.print(f"  ! backup {backup} holds {some} of its files ({status}): only the "
                      "files both backups hold are compared", style="yellow", highlight=False)
        for mark, key in (("+", "added"), ("-", "removed"), ("~", "changed")):
            for path in found[key]:
                out.print(f"  {mark} {path}", highlight=False)
    compared = [f for f in changes.values()
                if not (f["incomplete"] and set(f["incomplete"].values()) == {ABSENT})]
    if not any(any(f.values()) for f in changes.values()):
        out.print("No differences.")
    elif compared and not any(f[key] for f in compared
                              for key in ("added", "removed", "changed")):
        out.print("No differences in the files both backups hold.")


@backup_app.command()
def restore(backup_id: Annotated[str, typer.Argument(metavar="ID")],
            machine: Annotated[str, typer.Option(help="Whose files, as backed up")],
            path: Annotated[str | None, typer.Option(help=(
                "A file or folder of it, below its root as dncq backup show names it (O1234, "
                "USER/O2000) or whole (//CNC_MEM/O1234); default: all of it"))] = None,
            to: Annotated[str | None, typer.Option(
                "--to", metavar="MACHINE", help="Restore onto this machine")]
            = None,
            replace: Annotated[bool, typer.Option(
                "--replace", help="Replace files that are there")] = False,
            wait: WaitOpt = WAIT) -> None:
    """Send files of a backup back to a machine (a restore job)."""
    body = {"machine": machine, "path": path, "to": to, "replace": replace}
    job = api_call("POST", f"/api/backups/{segment(backup_id)}/restore", json=body,
                        if_it_got_there=MAYBE_RESTORING)
    out.print(f"Restore job {job['id']}: {counted(job['total'], 'file')}.")
    started(job["id"], wait)


@backup_app.command()
def prune(dry_run: Annotated[bool, typer.Option("--dry-run",
                                                help="List what would go, delete nothing")]
          = False) -> None:
    """Delete backups that their schedule's retention policy no longer keeps."""
    found = api_call("POST", "/api/schedules/prune", params={"dry_run": dry_run})
    verb = "Would delete" if dry_run else "Deleted"
    for name in found["pruned"]:
        out.print(f"{verb} {name}")
    out.print(f"{verb} {len(found['pruned'])} backups.")
