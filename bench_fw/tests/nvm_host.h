#ifndef BENCH_NVM_HOST_H
#define BENCH_NVM_HOST_H
extern unsigned char nvm_image[4096];
void nvm_erase();
#endif
