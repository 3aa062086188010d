"""The core, in three roles that only look down: ``formats`` (every file two steps share) over ``geometry``
(boxes, cameras, frames, the DSM and rays) over ``runtime`` (configuration, errors, logging, I/O, guard, GUI
helpers). It imports no step (docs/DESIGN.md §1)."""
