//! The GPIO output: one line through the Linux GPIO character device (uAPI v2).
