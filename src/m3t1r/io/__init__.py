"""Files in and out, on the ground layer: one module per concept, imported by module.

- `paths`: `StrPath`, `STDOUT` (`-`), `ensure_not_protected` (an output is never an input file);
- `pairing`: a URDF and its closures file: `paired_closures_path`, the sha256 a URDF records;
- `temporaries`: recognisable temporary files, their cleanup at exit, `sweep_locked` of a killed run's leftovers;
- `signals`: signals held during renames, `Terminated` and `termination_as_exception`;
- `strict_json`: `json_text`, JSON that any strict parser reads back;
- `outputs`: `OutputSet` (every output of a command checked first, committed as a unit),
  `atomic_write_bytes`, `atomic_write_text`;
- `tables`: validated numeric CSV tables (`read_table`, `Table`, `write_table`, `table_text`);
- `poses`: pose rows of a table (`POSE_COLUMNS`, `poses_from_table`, `pose_rows`);
- `progress`: `Progress` of long loops on stderr, `set_quiet`.

Imports flow paths -> pairing -> temporaries -> outputs -> tables -> poses; `signals`,
`strict_json` and `progress` stand alone. This `__init__` re-exports nothing: import a name from
its module (`from m3t1r.io.tables import read_table`), so the import graph shows which concept
each module uses.
"""
