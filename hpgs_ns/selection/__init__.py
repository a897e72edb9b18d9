"""The selection loop: when rounds run, what a selector sees, what each round records, early stop, the candidate
log and the snapshots. `config.SelectionConfig` is `--pipeline.selection.*`; `rounds.SelectionRounds` runs it.

Data flow: at a round step `rounds` builds a `SelectionContext` from the datamanager and the model, the selector
returns a `Selection`, the datamanager activates its views, and a `records.RoundRecord` is kept and logged.
Nothing is imported here, so that the datamanager can read `records` without loading the loop.
"""
