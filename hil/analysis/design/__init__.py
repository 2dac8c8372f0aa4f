"""Active design: the poses that decide a diagnosis' open questions and the rounds that measure them."""
