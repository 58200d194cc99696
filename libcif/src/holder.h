/*
 * holder.h - who holds a board's lock: one that keeps it for its life? [ours]
 *
 * A host that finds the board's transaction lock taken can only wait. That makes sense for
 * a short holder (another host's request, a download), not for the CiA 309 gateway
 * (`cifemu 309 serve`), which holds the lock as long as it runs: every wait would end in
 * DRV_CMD_ACTIVE a whole time-out later. The holder is found as host_api/holders.py finds
 * it: its pid in the kernel's table of file locks (/proc/locks: an flock's pid and the
 * file's device and inode), its words in /proc/PID/cmdline. Both files are read in a
 * bounded buffer; a malformed or overlong line or word matches nothing.
 */
#ifndef CIFEMU_HOLDER_H
#define CIFEMU_HOLDER_H

/* 1 when another process holds an flock on the file open at fd and is a CiA 309 gateway
   (its command line has the words "309" "serve" one after the other), else 0: also when
   /proc cannot tell. */
int cifemu_held_for_life(int fd);

/* The pieces, with the files as arguments (tests/c/holder_fuzz.c feeds them malformed
   tables): the pid of another process (not this one, not 0) with an flock on the file
   that the table names `where` ("MAJ:MIN:INODE", as /proc/locks prints it), else 0 ... */
long cifemu_flock_holder(const char *table, const char *where);
/* ... and whether a command line file (words ending in NULs) reads "... 309 serve ...". */
int cifemu_gateway_cmdline(const char *cmdline);

#endif
