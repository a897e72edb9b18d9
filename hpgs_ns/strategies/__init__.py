"""Trainer strategies: mechanisms that act on training (an extra loss term, something after views are added, before
or after backward), each one module with a config dataclass and the hooks of `base.Strategy`, listed in
`registry`. The model calls the hooks and knows no strategy by name. Importing this package imports nothing heavy."""
