"""Active design: the poses that decide a diagnosis' open questions and the rounds that measure them."""

# A round is measured in blocks this long and re-judged after each (sequential stopping). Here rather than in
# .plan, so that a procedure declares it as its default without importing the design and the diagnosis.
BLOCK_ROWS = 25
