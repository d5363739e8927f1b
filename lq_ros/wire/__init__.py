"""What travels between processes: topics and the one CDR codec every transport and every bag uses."""
