"""Control: the one vehicle authority, its command port and the operator's fleet commands."""
