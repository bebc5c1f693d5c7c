"""The artifact layer: each module opens a stage's input stores, calls the stage's pure functions
(``stex.<stage>``) and writes its store, previews and plots. The workflow's scripts call these."""
