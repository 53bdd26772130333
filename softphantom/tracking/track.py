"""The value object every tracker reader returns (:mod:`softphantom.records.track`), and what the
readers share (the body picker, the handling of a file cut short)."""

from softphantom.records.session import cut_row_note, drop_unterminated_line, warn_truncated
from softphantom.records.track import PoseTrack, make_track, pick_body

__all__ = ["PoseTrack", "cut_row_note", "drop_unterminated_line", "make_track", "pick_body", "warn_truncated"]
